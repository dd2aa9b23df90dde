// qemd's web page: sign in, resumable uploads (tus), the parameter form, the job list with live
// progress, and the before/after viewer. No framework: DOM calls and ES modules.
import { api, ApiProblem, authHeaders, download, setToken, token } from './api.js';
import { buildForm } from './form.js';

const $ = (id) => document.getElementById(id);
let form = null;
// The tenant's uploads as the server lists them (GET /v1/uploads), by id: a reload lists them
// again, with their file names.
const uploads = new Map();
let viewer = null;
let pollTimer = null;
const rows = new Map();

function show(el, text) { el.textContent = text || ''; el.hidden = !text; }
const problemText = (e) => (e instanceof ApiProblem ? `${e.status}: ${e.message}` : String(e?.message || e));

// ---- session ------------------------------------------------------------------------------

// `quiet`: the page's first try without a token, which a server with tokens refuses: the form
// then asks for one, without an error.
async function signIn(t, { quiet = false } = {}) {
  setToken(t);
  try {
    await api('/v1/jobs?limit=1');
  } catch (e) {
    if (token() === t) setToken('');
    if (quiet && e instanceof ApiProblem && e.status === 401) { $('token').focus(); return false; }
    show($('signin-error'), e instanceof ApiProblem && e.status === 401 ? 'Sign-in refused: the server does not know this token.' : `Sign-in failed: ${problemText(e)}`);
    return false;
  }
  show($('signin-error'), '');
  $('signin').hidden = true;
  $('session').hidden = false;
  $('whoami').textContent = t ? 'Signed in (token kept for this tab only)' : 'Open server: no token needed';
  $('signout').hidden = !t;
  $('main').hidden = false;
  $('intro').hidden = true;
  if (!form) await setUpForm();
  await loadUploads();
  poll();
  return true;
}

function signOut() {
  setToken('');
  uploads.clear();
  clearTimeout(pollTimer);
  rows.clear();
  $('job-rows').textContent = '';
  $('uploads').textContent = '';
  $('viewer').hidden = true;
  $('main').hidden = true;
  $('intro').hidden = false;
  $('signin').hidden = false;
  $('session').hidden = true;
  $('token').value = '';
  $('token').focus();
}

// ---- parameters ---------------------------------------------------------------------------

async function setUpForm() {
  const doc = await (await fetch('/openapi.json')).json();
  const schemas = doc.components.schemas;
  form = buildForm($('param-fields'), schemas.Params);
  const out = $('output_format');
  out.append(new Option('same as input', ''));
  for (const f of schemas.Format.enum) out.append(new Option(f, f));
}

async function submitJob(ev) {
  ev.preventDefault();
  show($('job-error'), '');
  const input = $('input').value;
  if (!input) { show($('job-error'), 'Upload a file first.'); return; }
  const body = { input, params: form.values() };
  if ($('output_format').value) body.output_format = $('output_format').value;
  $('submit').disabled = true;
  try {
    const job = await api('/v1/jobs', { method: 'POST', body });
    upsertRow(job);
    poll();
  } catch (e) {
    show($('job-error'), problemText(e));
    if (e.field) {
      const name = e.field.replace(/^params\./, '');
      document.querySelector(`[data-param="${CSS.escape(name)}"]`)?.focus();
    }
  } finally {
    $('submit').disabled = false;
  }
}

// ---- uploads ------------------------------------------------------------------------------

/** Fetches the tenant's complete uploads (newest first, up to 1000) and redraws the list. */
async function loadUploads() {
  try {
    const page = await api('/v1/uploads?limit=1000');
    for (const u of page.uploads) if (u.complete) uploads.set(u.id, u);
    show($('uploads-error'), '');
  } catch (e) { show($('uploads-error'), `Uploads: ${problemText(e)}`); }
  renderUploads();
}

function uploadName(u) { return u.filename || u.id.slice(0, 8); }

function renderUploads() {
  const sel = $('input');
  const keep = sel.value;
  sel.textContent = '';
  const list = [...uploads.values()].sort((a, b) => (a.created < b.created ? 1 : a.created > b.created ? -1 : 0));
  for (const u of list) {
    const what = u.faces != null ? `${u.points} vertices, ${u.faces} faces` : `${u.points ?? '?'} points`;
    sel.append(new Option(`${uploadName(u)} (${u.format}, ${what})`, u.id));
  }
  if (keep && uploads.has(keep)) sel.value = keep;
}

function uploadFile(file) {
  const li = document.createElement('li');
  const name = document.createElement('span');
  name.textContent = file.name;
  const pct = document.createElement('span');
  pct.className = 'pct';
  pct.textContent = '0 %';
  const bar = document.createElement('progress');
  bar.max = 100;
  bar.value = 0;
  bar.setAttribute('aria-label', `Upload of ${file.name}`);
  const err = document.createElement('span');
  err.className = 'error';
  err.setAttribute('role', 'alert');
  li.append(name, pct, bar, err);
  $('uploads').prepend(li);
  li.dataset.state = 'uploading';
  const upload = new window.tus.Upload(file, {
    endpoint: '/v1/uploads',
    chunkSize: 64 * 1024 * 1024,
    retryDelays: [0, 1000, 3000, 5000, 10000],
    metadata: { filename: file.name },
    headers: authHeaders(),
    removeFingerprintOnSuccess: true,
    onProgress(sent, total) {
      const p = total ? (100 * sent) / total : 0;
      bar.value = p;
      pct.textContent = `${p.toFixed(p < 100 ? 1 : 0)} %`;
    },
    async onSuccess() {
      const id = upload.url.split('/').pop();
      try {
        const u = await api(`/v1/uploads/${id}`);
        uploads.set(id, u);
        renderUploads();
        $('input').value = id;
        pct.textContent = `100 % · ${u.format}, ${u.points?.toLocaleString('en') ?? '?'} ${u.faces != null ? 'vertices' : 'points'}`;
        li.dataset.state = 'done';
        li.dataset.upload = id;
      } catch (e) { err.textContent = problemText(e); li.dataset.state = 'failed'; }
    },
    onError(e) {
      let text = String(e.message || e);
      const res = e.originalResponse;
      if (res) {
        try { const p = JSON.parse(res.getBody()); text = `${res.getStatus()}: ${p.detail}`; } catch { /* keep the client's message */ }
      }
      err.textContent = `Upload failed: ${text}`;
      li.dataset.state = 'failed';
    },
  });
  upload.findPreviousUploads().then((previous) => {
    if (previous.length) upload.resumeFromPreviousUpload(previous[0]);
    upload.start();
  });
}

// ---- jobs ---------------------------------------------------------------------------------

const fmtEta = (s) => (s == null || !Number.isFinite(s) ? '' : s < 90 ? `${Math.ceil(s)} s` : `${Math.round(s / 60)} min`);

// The ETA extrapolates the percentage's rate over the last 20 s the page watched (the early
// phases of a tiled run cover more percent per second than its tiles do), else over the run.
function eta(job, hist) {
  const p = job.progress?.percent;
  const run = job.timings?.run_s;
  if (job.status !== 'running' || !p || p < 1 || run == null) { hist.length = 0; return null; }
  const now = performance.now() / 1000;
  hist.push([now, p]);
  while (hist.length > 2 && now - hist[0][0] > 20) hist.shift();
  const [t0, p0] = hist[0];
  if (now - t0 >= 3 && p > p0) return ((100 - p) * (now - t0)) / (p - p0);
  return (run * (100 - p)) / p;
}

function button(label, onClick, cls) {
  const b = document.createElement('button');
  b.type = 'button';
  b.textContent = label;
  if (cls) b.className = cls;
  b.addEventListener('click', onClick);
  return b;
}

function upsertRow(job) {
  let r = rows.get(job.id);
  if (!r) {
    const tr = document.createElement('tr');
    tr.dataset.job = job.id;
    const cells = Array.from({ length: 8 }, () => document.createElement('td'));
    tr.append(...cells);
    const bar = document.createElement('progress');
    bar.max = 100;
    bar.setAttribute('aria-label', `Progress of job ${job.id.slice(0, 8)}`);
    const pct = document.createElement('span');
    pct.className = 'pct';
    cells[5].append(bar, ' ', pct);
    const actions = document.createElement('div');
    actions.className = 'actions';
    cells[7].append(actions);
    const view = button('View', () => openViewer(job.id), 'view');
    // Saved under the input's name (`scan.denoised.laz`), as the server's Content-Disposition says.
    const dl = button('Download', () => download(`/v1/jobs/${job.id}/result`, r.job.result?.filename || `${job.id}.${r.job.output_format}`).catch((e) => show($('jobs-error'), problemText(e))), 'download');
    const cancel = button('Cancel', () => cancelJob(job.id), 'cancel');
    actions.append(view, dl, cancel);
    $('job-rows').prepend(tr);
    r = { tr, cells, bar, pct, view, dl, cancel, job, hist: [] };
    rows.set(job.id, r);
  }
  r.job = job;
  const p = job.progress;
  r.tr.dataset.status = job.status;
  r.cells[0].textContent = job.id.slice(0, 8);
  r.cells[0].title = job.id;
  const up = uploads.get(job.input);
  r.cells[1].textContent = job.input_filename || (up && uploadName(up)) || job.input.slice(0, 8);
  r.cells[1].title = job.input;
  r.cells[2].textContent = job.status + (job.message ? `: ${job.message}` : '');
  r.cells[3].textContent = p?.phase ?? '';
  r.cells[4].textContent = p?.tiles_total ? `${p.tiles_done}/${p.tiles_total}` : '';
  const percent = p?.percent ?? (job.status === 'successful' ? 100 : 0);
  r.bar.value = percent;
  r.pct.textContent = `${percent >= 100 ? 100 : percent.toFixed(1)} %`;
  r.cells[6].textContent = fmtEta(eta(job, r.hist));
  const done = job.status === 'successful';
  r.view.disabled = !done;
  r.dl.disabled = !done;
  r.cancel.textContent = job.status === 'accepted' || job.status === 'running' ? 'Cancel' : 'Delete';
  r.cancel.hidden = job.status === 'dismissed';
}

async function cancelJob(id) {
  try {
    const job = await api(`/v1/jobs/${id}`, { method: 'DELETE' });
    upsertRow(job);
    if (viewer && viewer.job === id) $('viewer').hidden = true;
  } catch (e) { show($('jobs-error'), problemText(e)); }
}

async function poll() {
  clearTimeout(pollTimer);
  if (!$('main').hidden) {
    let active = false;
    try {
      const page = await api('/v1/jobs?limit=100');
      for (const j of page.jobs.slice().reverse()) {
        if (j.status === 'dismissed' && !rows.has(j.id)) continue;
        upsertRow(j);
        active ||= j.status === 'accepted' || j.status === 'running';
      }
      $('jobs-empty').hidden = rows.size > 0;
      show($('jobs-error'), '');
    } catch (e) {
      show($('jobs-error'), problemText(e));
      if (e instanceof ApiProblem && e.status === 401) { signOut(); return; }
    }
    pollTimer = setTimeout(poll, active ? 700 : 4000);
  }
}

// ---- viewer -------------------------------------------------------------------------------

async function openViewer(id) {
  const section = $('viewer');
  section.hidden = false;
  show($('viewer-error'), '');
  $('viewer-info').textContent = 'Loading the preview…';
  try {
    if (!viewer) {
      const { Viewer } = await import('./viewer.js');
      viewer = new Viewer({
        root: section, before: $('view-before'), after: $('view-after'), views: $('views'), colour: $('colour'),
        shadingLabel: $('shading-l'), scaleMax: $('scale-max'), info: $('viewer-info'), flip: $('flip'),
        legendBar: $('legend-bar'), legendLabels: $('legend-labels'),
      });
      $('colour').addEventListener('change', (e) => viewer.setColour(e.target.value));
      $('shading').addEventListener('change', (e) => viewer.setShading(e.target.value));
      $('layout').addEventListener('change', (e) => viewer.setLayout(e.target.value));
      $('psize').addEventListener('input', (e) => viewer.setPointSize(Number(e.target.value)));
      $('scale-max').addEventListener('change', (e) => viewer.setScaleMax(Number(e.target.value)));
      $('flip').addEventListener('click', () => viewer.flip());
      $('reset-view').addEventListener('click', () => viewer.resetView());
      $('close-viewer').addEventListener('click', () => { section.hidden = true; });
    }
    await viewer.load(id);
    section.scrollIntoView({ block: 'start' });
    $('view-after').focus({ preventScroll: true });
  } catch (e) {
    $('viewer-info').textContent = '';
    show($('viewer-error'), `Preview failed: ${problemText(e)}`);
  }
}

// ---- wiring -------------------------------------------------------------------------------

function wire() {
  $('signin').addEventListener('submit', (e) => { e.preventDefault(); signIn($('token').value.trim()); });
  $('signout').addEventListener('click', signOut);
  $('job-form').addEventListener('submit', submitJob);
  $('reset-params').addEventListener('click', () => form?.reset());
  const drop = $('drop');
  const pick = $('file');
  $('choose').addEventListener('click', () => pick.click());
  pick.addEventListener('change', () => { for (const f of pick.files) uploadFile(f); pick.value = ''; });
  drop.addEventListener('dragover', (e) => { e.preventDefault(); drop.classList.add('over'); });
  drop.addEventListener('dragleave', () => drop.classList.remove('over'));
  drop.addEventListener('drop', (e) => { e.preventDefault(); drop.classList.remove('over'); for (const f of e.dataTransfer.files) uploadFile(f); });
  document.body.dataset.app = 'ready';
  // A stored token signs in again; without one the page tries the server as it is, so a server
  // without tokens (as `qemd serve` starts by default) opens without asking for one.
  if (sessionStorage.getItem('qemd.token') !== null) signIn(token());
  else signIn('', { quiet: true });
}

wire();
