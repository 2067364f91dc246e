// The slice viewer: one volume ([z][y][x] float32 .npy) shown axial, coronal and sagittal. The axial slice
// under the cursor comes first by a byte range of the .npy (the first picture needs one slice, not the
// volume); the whole volume follows for the other planes. Window/level is applied in the browser.

import { bytes } from './api.js';
import { clear, errorBox, h } from './dom.js';
import { expectedOffset, parseHeader } from './npy.js';
import { PlaneView } from './sliceview.js';

/** Window presets in HU (the API's: width, level). */
export const PRESETS = {
  soft_tissue: [400, 40], lung: [1500, -600], liver: [150, 90], bone: [2500, 480], brain: [80, 40],
};
const MU_WATER = 0.0192; // the API's default μ of water, 1/mm

/**
 * The preset a clinical viewer opens CT data with, chosen from the values of a slice in HU: mostly bone
 * (little soft tissue) → bone; much lung parenchyma → lung; bone around soft tissue with almost no fat or
 * lung (a head) → brain; any other body → soft tissue. Fractions are of the voxels above −950 HU (the
 * object, not the air around it). Returns [name, reason].
 */
export function presetFor(hu) {
  let n = 0; let lung = 0; let bone = 0; let soft = 0; let fat = 0;
  const step = Math.max(1, Math.floor(hu.length / 40000));
  for (let x = 0; x < hu.length; x += step) {
    const v = hu[x];
    if (!(v > -950)) continue;
    n += 1;
    if (v < -500) lung += 1;
    else if (v > 300) bone += 1;
    else if (v >= -150 && v <= -50) fat += 1;
    if (v >= -200 && v <= 200) soft += 1;
  }
  if (n === 0) return ['soft_tissue', 'no tissue in the slice'];
  const f = (c) => c / n;
  if (f(bone) > 0.3 && f(soft) < 0.2) return ['bone', `${Math.round(100 * f(bone))} % bone`];
  if (f(lung) > 0.25) return ['lung', `${Math.round(100 * f(lung))} % lung`];
  if (f(bone) > 0.05 && f(fat) < 0.05 && f(lung) < 0.02) return ['brain', 'bone around soft tissue, no fat'];
  return ['soft_tissue', 'soft tissue'];
}

/** Whether values in 1/mm read as a CT of real matter: air near −1000 HU, the rest below 4000 HU. */
function looksLikeHu(hu) {
  const sample = [];
  const step = Math.max(1, Math.floor(hu.length / 20000));
  for (let x = 0; x < hu.length; x += step) sample.push(hu[x]);
  sample.sort((a, b) => a - b);
  const lo = sample[Math.floor(sample.length * 0.005)];
  const hi = sample[Math.floor(sample.length * 0.995)];
  return lo > -1100 && lo < -850 && hi < 4000;
}

export class SliceViewer {
  /** opts: {url, frame (LPS) or null, units ('hu' | 'mu_per_mm'), grid} */
  constructor(root, opts) {
    this.root = root;
    this.opts = opts;
    this.units = opts.units;
    this.patient = Boolean(opts.frame);
    this.slices = new Map(); // axial index -> Float32Array while the volume loads
    this.volume = null;
    this.views = [];
    this.window = { ww: 1, wl: 0 };
    this.onResize = () => this.layout();
    // The views are laid out for the width of their container, whatever changes it: the window, or a
    // scroll bar that appears once the page below has grown.
    this.resizes = new ResizeObserver(() => {
      if (this.grid && this.grid.clientWidth !== this.laidOutFor) this.layout();
    });
  }

  destroy() {
    window.removeEventListener('resize', this.onResize);
    this.resizes.disconnect();
    if (this.ctl) this.ctl.abort();
  }

  async start(signal) {
    const t0 = performance.now();
    this.ctl = new AbortController();
    signal.addEventListener('abort', () => this.ctl.abort());
    // The middle axial slice is asked for together with the header, at the offset the job's result shape
    // gives; it is used only if the header read agrees (one round trip instead of two on the way to the
    // first picture).
    const early = this.earlySlice();
    const head = parseHeader(await bytes(this.opts.url, [0, 1023], this.ctl.signal));
    if (head.dtype !== '<f4') throw new Error(`unsupported volume dtype ${head.dtype}`);
    const s = head.shape.length === 2 ? [1, ...head.shape] : head.shape;
    this.offset = head.offset;
    this.n = [s[2], s[1], s[0]]; // [nx, ny, nz]
    const f = this.opts.frame;
    this.spacing = f ? f.spacing_mm : this.gridSpacing();
    this.spacingKnown = Boolean(f) || Boolean(this.gridSpacing(true));
    this.cursor = this.n.map((x) => Math.floor(x / 2));
    this.status = h('span.muted.load-status', 'loading the volume…');
    this.build();
    if (early && early.offset === this.offset && early.k === this.cursor[2]
        && early.shape.join() === s.join()) {
      this.slices.set(early.k, new Float32Array(await early.data));
      this.root.dataset.firstSliceEarly = 'true';
    } else {
      await this.loadAxial(this.cursor[2]);
    }
    const first = this.slices.get(this.cursor[2]);
    this.defaultWindow(first);
    this.redraw();
    // Since the page's navigation started (performance.now's origin), and since the viewer started.
    this.root.dataset.firstSliceMs = performance.now().toFixed(1);
    this.root.dataset.viewerMs = (performance.now() - t0).toFixed(1);
    this.loadAll().catch((e) => {
      if (e.name !== 'AbortError') this.status.replaceWith(errorBox(e));
    });
  }

  /** The request of the middle axial slice made before the header is read, or null without a 3D shape. */
  earlySlice() {
    const shape = this.opts.shape;
    if (!Array.isArray(shape) || shape.length !== 3 || !shape.every((n) => Number.isInteger(n) && n > 0)) {
      return null;
    }
    const offset = expectedOffset(shape);
    const k = Math.floor(shape[0] / 2);
    const size = shape[1] * shape[2] * 4;
    const data = bytes(this.opts.url, [offset + k * size, offset + (k + 1) * size - 1], this.ctl.signal);
    data.catch(() => {}); // a failure is the header's to report, or the fallback's
    return { shape, offset, k, data };
  }

  gridSpacing(strict) {
    const g = this.opts.grid || {};
    if (Array.isArray(g.spacing_mm)) return g.spacing_mm;
    if (g.dx_mm) return [g.dx_mm, g.dy_mm || g.dx_mm, g.dx_mm];
    return strict ? null : [1, 1, 1];
  }

  sliceBytes() {
    return this.n[0] * this.n[1] * 4;
  }

  async loadAxial(k) {
    if (this.volume || this.slices.has(k)) return;
    const start = this.offset + k * this.sliceBytes();
    const buf = await bytes(this.opts.url, [start, start + this.sliceBytes() - 1], this.ctl.signal);
    this.slices.set(k, new Float32Array(buf));
  }

  async loadAll() {
    const buf = await bytes(this.opts.url, null, this.ctl.signal);
    const n = this.n[0] * this.n[1] * this.n[2];
    this.volume = new Float32Array(buf.slice(this.offset, this.offset + 4 * n));
    this.slices.clear();
    this.status.textContent = '';
    this.root.dataset.volumeLoaded = 'true';
    this.redraw();
  }

  /** A plane's slice as a row-major [row][column] array in storage order, or null while loading. */
  sliceData(name) {
    const [nx, ny, nz] = this.n;
    const [i, j, k] = this.cursor;
    if (name === 'axial') {
      if (this.volume) return this.volume.subarray(k * nx * ny, (k + 1) * nx * ny);
      const s = this.slices.get(k);
      if (!s) this.loadAxial(k).then(() => this.redraw('axial')).catch(() => {});
      return s || null;
    }
    if (!this.volume) return null;
    const v = this.volume;
    if (name === 'coronal') {
      const out = new Float32Array(nx * nz);
      for (let z = 0; z < nz; z += 1) out.set(v.subarray(z * nx * ny + j * nx, z * nx * ny + (j + 1) * nx), z * nx);
      return out;
    }
    const out = new Float32Array(ny * nz);
    for (let z = 0; z < nz; z += 1) {
      for (let y = 0; y < ny; y += 1) out[z * ny + y] = v[z * nx * ny + y * nx + i];
    }
    return out;
  }

  valueAt([i, j, k]) {
    const [nx, ny] = this.n;
    if (this.volume) return this.volume[(k * ny + j) * nx + i];
    const s = this.slices.get(k);
    return s ? s[j * nx + i] : null;
  }

  /** LPS mm of a voxel (frame), or grid-centred coordinates without one. */
  position(v) {
    const f = this.opts.frame;
    if (f) {
      const d = f.direction || [[1, 0, 0], [0, 1, 0], [0, 0, 1]];
      return [0, 1, 2].map((a) => f.origin_mm[a] + v[0] * f.spacing_mm[0] * d[0][a]
        + v[1] * f.spacing_mm[1] * d[1][a] + v[2] * f.spacing_mm[2] * d[2][a]);
    }
    return [0, 1, 2].map((a) => (v[a] - (this.n[a] - 1) / 2) * this.spacing[a]);
  }

  /** Data units per preset HU. */
  toUnits(hu) {
    return this.units === 'hu' ? hu : MU_WATER * (1 + hu / 1000);
  }

  windowScale() {
    return this.units === 'hu' ? 1000 : MU_WATER;
  }

  /**
   * The window the viewer opens with: on CT values (HU, or 1/mm that read as HU) a preset chosen from the
   * data (`presetFor`), as clinical viewers do; otherwise (simulations, phantoms in arbitrary units) the
   * 0.5–99.5 % range of the slice. The choice is shown in the preset menu and as `data-preset`.
   */
  defaultWindow(data) {
    if (!data || !data.length) return;
    const hu = this.units === 'hu' ? data : Float32Array.from(data, (v) => 1000 * (v - MU_WATER) / MU_WATER);
    if (this.units === 'hu' || looksLikeHu(hu)) {
      const [name, reason] = presetFor(hu);
      this.applyPreset(name, true);
      this.root.dataset.preset = name;
      this.root.dataset.presetReason = reason;
      this.presetMenu.value = name;
      this.presetMenu.title = `chosen from the data: ${reason}`;
    } else {
      this.autoWindow(data);
      this.root.dataset.preset = 'auto';
      this.presetMenu.value = 'auto';
    }
  }

  applyPreset(name, quiet) {
    const p = PRESETS[name];
    if (p) this.setWindow(this.toUnits(p[0]) - (this.units === 'hu' ? 0 : MU_WATER), this.toUnits(p[1]), quiet);
  }

  autoWindow(data) {
    if (!data || !data.length) return;
    const sample = [];
    const step = Math.max(1, Math.floor(data.length / 20000));
    for (let x = 0; x < data.length; x += step) sample.push(data[x]);
    sample.sort((a, b) => a - b);
    const lo = sample[Math.floor(sample.length * 0.005)];
    const hi = sample[Math.floor(sample.length * 0.995)];
    this.setWindow(Math.max(hi - lo, 1e-6), (hi + lo) / 2, true);
  }

  setWindow(ww, wl, quiet) {
    this.window = { ww, wl };
    this.wwInput.value = String(+ww.toPrecision(5));
    this.wlInput.value = String(+wl.toPrecision(5));
    this.root.dataset.ww = String(ww);
    this.root.dataset.wl = String(wl);
    if (!quiet) this.redraw();
  }

  step(name, by) {
    const a = { axial: 2, coronal: 1, sagittal: 0 }[name];
    const next = Math.max(0, Math.min(this.n[a] - 1, this.cursor[a] + by));
    if (next === this.cursor[a]) return;
    this.cursor[a] = next;
    this.redraw(name);
  }

  moveCursor(v) {
    this.cursor = v;
    this.redraw();
  }

  /** Draw on the next frame: `only` that plane (the others redraw their crosshairs), or every plane. */
  redraw(only) {
    this.dirty = this.dirty || new Set();
    this.dirty.add(only || 'all');
    if (this.pending) return;
    this.pending = requestAnimationFrame(() => {
      const dirty = this.dirty;
      this.pending = 0;
      this.dirty = null;
      for (const v of this.views) {
        if (dirty.has('all') || dirty.has(v.name)) v.draw();
        else v.cross();
      }
    });
  }

  layout() {
    const wide = this.grid.clientWidth;
    this.laidOutFor = wide;
    const cols = wide >= 900 ? 3 : wide >= 560 ? 2 : 1;
    const boxW = Math.floor((wide - (cols - 1) * 8) / cols) - 8;
    const boxH = Math.max(200, Math.min(boxW, window.innerHeight - 200));
    for (const v of this.views) v.layout(boxW, boxH);
    this.redraw();
  }

  build() {
    const presets = h('select#wl-preset', { 'aria-label': 'window preset' },
      h('option', { value: '' }, 'window preset…'),
      Object.keys(PRESETS).map((p) => h('option', { value: p }, p.replace('_', ' '))),
      h('option', { value: 'auto' }, 'auto (0.5–99.5 %)'));
    presets.addEventListener('change', () => {
      if (PRESETS[presets.value]) this.applyPreset(presets.value);
      else if (presets.value === 'auto') this.autoWindow(this.sliceData('axial'));
      this.root.dataset.preset = presets.value;
      this.redraw();
    });
    this.presetMenu = presets;
    this.wwInput = h('input#wl-width', { type: 'number', step: 'any', 'aria-label': 'window width' });
    this.wlInput = h('input#wl-level', { type: 'number', step: 'any', 'aria-label': 'window level' });
    const apply = () => {
      const ww = Number(this.wwInput.value);
      const wl = Number(this.wlInput.value);
      if (Number.isFinite(ww) && ww > 0 && Number.isFinite(wl)) this.setWindow(ww, wl);
    };
    this.wwInput.addEventListener('change', apply);
    this.wlInput.addEventListener('change', apply);
    const unit = this.units === 'hu' ? 'HU' : '1/mm';
    const planes = this.n[2] > 1 ? ['axial', 'coronal', 'sagittal'] : ['axial'];
    this.views = planes.map((p) => new PlaneView(this, p));
    this.grid = h('div.views', this.views.map((v) => v.el));
    clear(this.root).append(h('h2', 'Slices'),
      h('div.row.toolbar', presets, h('label', 'W ', this.wwInput), h('label', 'L ', this.wlInput),
        h('span.muted', unit), this.status,
        h('span.muted.hint', 'wheel (a slice per notch) or ↑↓ scroll · right-drag window · click to link')),
      this.grid);
    window.addEventListener('resize', this.onResize);
    this.resizes.observe(this.grid);
    this.layout();
  }
}
