// Colour scales of the viewer: piecewise-linear ramps over a few control colours, the ASPRS
// LAS class palette, and a legend drawer.

const HEAT = [[0.05, 0.03, 0.25], [0.15, 0.25, 0.75], [0.1, 0.7, 0.85], [0.55, 0.9, 0.3], [0.98, 0.85, 0.15], [0.95, 0.35, 0.1], [0.75, 0.05, 0.1]];
const TERRAIN = [[0.15, 0.25, 0.6], [0.2, 0.6, 0.55], [0.45, 0.7, 0.3], [0.8, 0.75, 0.4], [0.6, 0.45, 0.3], [0.95, 0.95, 0.95]];
const GREY = [[0.08, 0.08, 0.08], [1, 1, 1]];

export const RAMPS = { displacement: HEAT, height: TERRAIN, intensity: GREY };

/** The colour of `t` in 0..1 on `ramp`, written into out[o..o+3]. */
export function rampInto(ramp, t, out, o) {
  const x = Math.min(1, Math.max(0, Number.isFinite(t) ? t : 0)) * (ramp.length - 1);
  const i = Math.min(ramp.length - 2, Math.floor(x));
  const f = x - i;
  const a = ramp[i], b = ramp[i + 1];
  out[o] = a[0] + (b[0] - a[0]) * f;
  out[o + 1] = a[1] + (b[1] - a[1]) * f;
  out[o + 2] = a[2] + (b[2] - a[2]) * f;
}

// ASPRS LAS 1.4 standard classes (R15): colours as commonly shown.
const CLASSES = {
  0: [0.6, 0.6, 0.6], 1: [0.75, 0.75, 0.75], 2: [0.6, 0.42, 0.24], 3: [0.55, 0.8, 0.45], 4: [0.3, 0.65, 0.3],
  5: [0.1, 0.45, 0.15], 6: [0.9, 0.3, 0.2], 7: [1, 0, 1], 8: [1, 1, 0], 9: [0.2, 0.45, 0.95], 10: [0.9, 0.6, 0.1],
  11: [0.3, 0.3, 0.3], 12: [0.9, 0.9, 0.6], 13: [0.8, 0.8, 0.2], 14: [0.9, 0.7, 0.2], 15: [0.6, 0.2, 0.8],
  16: [0.2, 0.8, 0.8], 17: [0.5, 0.5, 0.8], 18: [1, 0.5, 0.8],
};
export const CLASS_NAMES = { 0: 'never classified', 1: 'unclassified', 2: 'ground', 3: 'low veg.', 4: 'medium veg.', 5: 'high veg.', 6: 'building', 7: 'noise', 9: 'water', 17: 'bridge deck', 18: 'high noise' };

export function classInto(c, out, o) {
  const k = CLASSES[c] || [0.5 + ((c * 37) % 50) / 100, 0.4, 0.5 + ((c * 53) % 50) / 100];
  out[o] = k[0]; out[o + 1] = k[1]; out[o + 2] = k[2];
}

/** Draws `ramp` into a canvas of the legend. */
export function drawRamp(canvas, ramp) {
  const g = canvas.getContext('2d');
  const c = new Float32Array(3);
  for (let x = 0; x < canvas.width; x++) {
    rampInto(ramp, x / (canvas.width - 1), c, 0);
    g.fillStyle = `rgb(${c[0] * 255 | 0},${c[1] * 255 | 0},${c[2] * 255 | 0})`;
    g.fillRect(x, 0, 1, canvas.height);
  }
}

/**
 * A length in the input's units, labelled as its CRS says (`unit`, the preview's `units`):
 * metres with a sensible prefix, feet (`ft`, `US ft`) or degrees as they are, and without a
 * declared unit the bare number in "units" (a mesh of unknown scale is not in millimetres).
 */
export function length(v, unit) {
  if (!Number.isFinite(v)) return '–';
  const a = Math.abs(v);
  if (unit === 'm') {
    if (a === 0) return '0 m';
    if (a < 1e-3) return `${(v * 1e6).toPrecision(3)} µm`;
    if (a < 1) return `${(v * 1e3).toPrecision(3)} mm`;
    return `${v.toPrecision(4)} m`;
  }
  const n = a === 0 ? '0' : a >= 1e5 ? v.toFixed(1) : v.toPrecision(4);
  return `${n} ${unit || 'units'}`;
}
