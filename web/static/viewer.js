// The before/after viewer: two WebGL canvases sharing one camera (orbit controls on either move
// both), points or a shaded mesh from the job's preview PLY files, coloured by displacement,
// height, intensity or class.
import * as THREE from 'three';
import { OrbitControls } from 'three/addons/controls/OrbitControls.js';
import { PLYLoader } from 'three/addons/loaders/PLYLoader.js';
import { api, binary } from './api.js';
import { RAMPS, rampInto, classInto, drawRamp, length, CLASS_NAMES } from './colours.js';

function parsePly(buf) {
  const loader = new PLYLoader();
  loader.setCustomPropertyNameMapping({ displacement: ['displacement'], intensity: ['intensity'], klass: ['class'] });
  return loader.parse(buf);
}

function quantiles(arr, qs) {
  const s = Float32Array.from(arr).sort();
  return qs.map((q) => (s.length ? s[Math.min(s.length - 1, Math.round((s.length - 1) * q))] : 0));
}

export class Viewer {
  constructor(els) {
    this.els = els;
    this.views = [els.before, els.after].map((canvas) => {
      const renderer = new THREE.WebGLRenderer({ canvas, antialias: false, preserveDrawingBuffer: true });
      renderer.setPixelRatio(Math.min(2, window.devicePixelRatio || 1));
      const scene = new THREE.Scene();
      scene.background = new THREE.Color(0x20242c);
      return { canvas, renderer, scene, object: null, geometry: null };
    });
    this.camera = new THREE.PerspectiveCamera(45, 1, 0.01, 1000);
    const light = new THREE.DirectionalLight(0xffffff, 2.2);
    light.position.set(1, 1, 2);
    this.camera.add(light);
    for (const v of this.views) v.scene.add(new THREE.HemisphereLight(0xffffff, 0x404040, 1.2));
    this.controls = this.views.map((v) => {
      const c = new OrbitControls(this.camera, v.canvas);
      c.addEventListener('change', () => this.render());
      return c;
    });
    for (const v of this.views) v.canvas.addEventListener('keydown', (e) => this.key(e));
    this.colour = 'displacement';
    this.shading = 'smooth';
    this.pointSize = 2;
    this.shown = 'after';
    this.layout = 'side';
    this.meta = null;
    new ResizeObserver(() => this.resize()).observe(els.before.parentElement.parentElement);
  }

  /** Loads job `id`'s preview; resolves when both sides are drawn. */
  async load(id) {
    this.els.root.dataset.ready = 'false';
    const meta = await api(`/v1/jobs/${id}/preview`);
    const [b, a] = await Promise.all([binary(`/v1/jobs/${id}/preview/before`), binary(`/v1/jobs/${id}/preview/after`)]);
    this.meta = meta;
    this.job = id;
    const unit = document.getElementById('scale-unit');
    if (unit) unit.textContent = meta.units || 'input units';
    const geoms = [parsePly(b), parsePly(a)];
    const mesh = meta.kind === 'mesh';
    this.up = mesh ? 1 : 2;
    this.camera.up.set(0, mesh ? 1 : 0, mesh ? 0 : 1);
    for (let i = 0; i < 2; i++) {
      const v = this.views[i];
      if (v.object) { v.scene.remove(v.object); v.geometry.dispose(); v.object.material.dispose(); }
      const g = geoms[i];
      g.setAttribute('color', new THREE.BufferAttribute(new Float32Array(g.attributes.position.count * 3), 3));
      let obj;
      if (mesh) {
        g.computeVertexNormals();
        obj = new THREE.Mesh(g, new THREE.MeshStandardMaterial({ vertexColors: true, flatShading: this.shading === 'flat', side: THREE.DoubleSide, roughness: 0.85, metalness: 0 }));
      } else {
        obj = new THREE.Points(g, new THREE.PointsMaterial({ size: this.pointSize, sizeAttenuation: false, vertexColors: true }));
      }
      v.scene.add(obj);
      v.object = obj;
      v.geometry = g;
    }
    this.views[0].scene.add(this.camera);
    const pos = geoms[0].attributes.position;
    const up = [];
    for (let i = 0; i < pos.count; i += Math.max(1, Math.floor(pos.count / 200000))) up.push(pos.getComponent(i, this.up));
    [this.upLo, this.upHi] = quantiles(up, [0.005, 0.995]);
    const inten = geoms[0].attributes.intensity;
    if (inten) [this.iLo, this.iHi] = quantiles(inten.array, [0.01, 0.99]);
    const d = meta.displacement;
    this.scaleMax = d ? (d.p99 > 0 ? d.p99 : d.max || 1) : 1;
    this.els.scaleMax.value = String(+this.scaleMax.toPrecision(3));
    const opts = this.els.colour.options;
    for (const o of opts) {
      o.disabled = (o.value === 'displacement' && !meta.paired) || (o.value === 'intensity' && !meta.intensity) || (o.value === 'class' && !meta.class);
    }
    if (opts[this.els.colour.selectedIndex].disabled) this.els.colour.value = meta.paired ? 'displacement' : 'height';
    this.els.shadingLabel.hidden = !mesh;
    this.setColour(this.els.colour.value);
    this.resetView();
    this.els.info.textContent = this.describe(meta);
    this.els.root.dataset.ready = 'true';
    this.els.root.dataset.job = id;
  }

  /** A length in the preview's units. */
  len(v) { return length(v, this.meta?.units); }

  describe(m) {
    const n = m.points_before.toLocaleString('en');
    const tot = m.points_total.toLocaleString('en');
    const what = m.kind === 'mesh' ? `${n} vertices, ${m.triangles.toLocaleString('en')} triangles` : `${n} of ${tot} points (${m.selection})`;
    const disp = m.displacement ? ` · moved: mean ${this.len(m.displacement.mean)}, p95 ${this.len(m.displacement.p95)}, max ${this.len(m.displacement.max)}` : ' · not paired (outliers removed): no displacement';
    return `${what}${disp}`;
  }

  resetView() {
    const g = this.views[0].geometry;
    if (!g) return;
    g.computeBoundingSphere();
    const s = g.boundingSphere;
    for (const c of this.controls) c.target.copy(s.center);
    const fit = Math.min(1, this.camera.aspect || 1);
    const dist = (s.radius / Math.tan((this.camera.fov * Math.PI) / 360) / fit) * 0.95;
    const dir = this.up === 2 ? new THREE.Vector3(0.0, -0.75, 0.66) : new THREE.Vector3(0.35, 0.25, 1);
    this.camera.position.copy(s.center).addScaledVector(dir.normalize(), dist);
    this.camera.near = Math.max(dist / 1000, s.radius / 1e4);
    this.camera.far = dist + s.radius * 4;
    this.camera.updateProjectionMatrix();
    for (const c of this.controls) c.update();
    this.render();
  }

  key(e) {
    const step = e.shiftKey ? 0.2 : 0.05;
    const c = this.controls[0];
    const off = this.camera.position.clone().sub(c.target);
    const up = this.camera.up.clone();
    let handled = true;
    if (e.key === 'ArrowLeft' || e.key === 'ArrowRight') {
      off.applyAxisAngle(up, e.key === 'ArrowLeft' ? -step * 4 : step * 4);
    } else if (e.key === 'ArrowUp' || e.key === 'ArrowDown') {
      const side = new THREE.Vector3().crossVectors(off, up).normalize();
      off.applyAxisAngle(side, e.key === 'ArrowUp' ? step * 4 : -step * 4);
    } else if (e.key === '+' || e.key === '=') off.multiplyScalar(1 - step * 2);
    else if (e.key === '-') off.multiplyScalar(1 + step * 2);
    else if (e.key === 't' || e.key === 'T') { this.flip(); return; }
    else if (e.key === 'r' || e.key === 'R') { this.resetView(); return; }
    else handled = false;
    if (!handled) return;
    e.preventDefault();
    this.camera.position.copy(c.target).add(off);
    for (const k of this.controls) k.update();
    this.render();
  }

  setColour(mode) {
    this.colour = mode;
    this.els.root.dataset.colour = mode;
    for (const v of this.views) if (v.geometry) this.paint(v.geometry, mode);
    this.legend();
    this.render();
  }

  setScaleMax(x) {
    if (Number.isFinite(x) && x > 0) { this.scaleMax = x; if (this.colour === 'displacement') this.setColour('displacement'); }
  }

  paint(g, mode) {
    const col = g.attributes.color.array;
    const n = g.attributes.position.count;
    const pos = g.attributes.position;
    if (mode === 'displacement' && g.attributes.displacement) {
      const d = g.attributes.displacement.array;
      for (let i = 0; i < n; i++) rampInto(RAMPS.displacement, d[i] / this.scaleMax, col, i * 3);
    } else if (mode === 'height') {
      const span = this.upHi - this.upLo || 1;
      for (let i = 0; i < n; i++) rampInto(RAMPS.height, (pos.getComponent(i, this.up) - this.upLo) / span, col, i * 3);
    } else if (mode === 'intensity' && g.attributes.intensity) {
      const a = g.attributes.intensity.array, span = this.iHi - this.iLo || 1;
      for (let i = 0; i < n; i++) rampInto(RAMPS.intensity, (a[i] - this.iLo) / span, col, i * 3);
    } else if (mode === 'class' && g.attributes.klass) {
      const a = g.attributes.klass.array;
      for (let i = 0; i < n; i++) classInto(a[i], col, i * 3);
    } else {
      col.fill(0.82);
    }
    g.attributes.color.needsUpdate = true;
  }

  legend() {
    const { legendBar, legendLabels } = this.els;
    const m = this.meta;
    legendLabels.textContent = '';
    const label = (t) => { const s = document.createElement('span'); s.textContent = t; legendLabels.append(s); };
    legendBar.hidden = !(this.colour in RAMPS);
    if (this.colour === 'displacement') {
      drawRamp(legendBar, RAMPS.displacement);
      label(`displacement: ${this.len(0)}`);
      label(this.len(this.scaleMax / 2));
      label(`≥ ${this.len(this.scaleMax)}`);
      if (m?.displacement) label(`(p99 ${this.len(m.displacement.p99)}, max ${this.len(m.displacement.max)})`);
    } else if (this.colour === 'height') {
      drawRamp(legendBar, RAMPS.height);
      const o = m ? m.origin[this.up] : 0;
      label(`height (${'xyz'[this.up]}): ${this.len(o + this.upLo)}`);
      label(this.len(o + this.upHi));
    } else if (this.colour === 'intensity') {
      drawRamp(legendBar, RAMPS.intensity);
      label(`intensity ${Math.round(this.iLo)} – ${Math.round(this.iHi)}`);
    } else if (this.colour === 'class') {
      const seen = new Set(this.views[0].geometry?.attributes.klass?.array ?? []);
      label(`classes: ${[...seen].sort((a, b) => a - b).map((c) => `${c} ${CLASS_NAMES[c] || ''}`.trim()).join(', ')}`);
    }
  }

  setShading(mode) {
    this.shading = mode;
    for (const v of this.views) {
      if (v.object?.isMesh) { v.object.material.flatShading = mode === 'flat'; v.object.material.needsUpdate = true; }
    }
    this.render();
  }

  setPointSize(s) {
    this.pointSize = s;
    for (const v of this.views) if (v.object?.isPoints) v.object.material.size = s;
    this.render();
  }

  setLayout(layout) {
    this.layout = layout;
    this.els.views.classList.toggle('toggle', layout === 'toggle');
    this.els.flip.hidden = layout !== 'toggle';
    this.applyShown();
  }

  flip() {
    if (this.layout !== 'toggle') return;
    this.shown = this.shown === 'after' ? 'before' : 'after';
    this.applyShown();
  }

  applyShown() {
    const toggle = this.layout === 'toggle';
    this.els.before.parentElement.hidden = toggle && this.shown !== 'before';
    this.els.after.parentElement.hidden = toggle && this.shown !== 'after';
    this.els.flip.textContent = `Showing: ${this.shown} (press T)`;
    this.els.flip.setAttribute('aria-pressed', String(this.shown === 'before'));
    this.els.root.dataset.shown = toggle ? this.shown : 'both';
    this.resize();
  }

  resize() {
    for (const v of this.views) {
      const w = v.canvas.clientWidth, h = v.canvas.clientHeight;
      if (w > 0 && h > 0) v.renderer.setSize(w, h, false);
    }
    const c = this.views.find((v) => v.canvas.clientWidth > 0)?.canvas;
    if (c) { this.camera.aspect = c.clientWidth / c.clientHeight; this.camera.updateProjectionMatrix(); }
    this.render();
  }

  render() {
    if (this.pending) return;
    this.pending = true;
    requestAnimationFrame(() => {
      this.pending = false;
      for (const v of this.views) {
        if (v.canvas.clientWidth === 0) continue;
        // One camera, two scenes: the light rides with the camera, so attach it to the scene drawn.
        v.scene.add(this.camera);
        v.renderer.render(v.scene, this.camera);
      }
      this.els.root.dataset.frames = String(Number(this.els.root.dataset.frames || 0) + 1);
    });
  }
}
