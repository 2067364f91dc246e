// A volume job's products: image stacks (projections, MIP/MinIP, thick slabs, MPR and curved planes,
// rotating MIPs) fetched once as float32 .npy and windowed in the browser, stepped frame by frame or played
// as a loop; renderings (volume rendering, shaded surfaces) shown as the server's RGB PNG frames and, for a
// rotation, its animated PNG, beside their parameters; meshes open in the WebGL view (mesh.js, on demand).

import { blobUrl, bytes } from './api.js';
import { clear, errorBox, fmtNum, h } from './dom.js';
import { decode } from './npy.js';
import { PRESETS } from './slices.js';

const MU_WATER = 0.0192;

/** The orientation letters around a product's image: frame `k`'s own sides where its frames face
 * different ways (`frame_orientations`, a rotation), else the sides all frames share. */
function sidesOf(p, k) {
  return (p.frame_orientations || [])[k] || p.orientation || {};
}

function orientLabels(p, k) {
  return ['top', 'bottom', 'left', 'right'].map((s) =>
    h(`span.orient.orient-${s}`, { dataset: { side: s } }, sidesOf(p, k)[s] || ''));
}

function setOrientLabels(stage, p, k) {
  const o = sidesOf(p, k);
  for (const el of stage.querySelectorAll('span.orient')) el.textContent = o[el.dataset.side] || '';
}

class StackView {
  constructor(job, p) {
    this.job = job;
    this.p = p;
    this.hu = (job.result.units || 'hu') === 'hu';
    this.frame = 0;
    this.canvas = h('canvas.product-image');
    this.stage = h('div.product-stage', this.canvas, orientLabels(p, 0));
    this.slider = h('input.frame', { type: 'range', min: '0', max: '0', value: '0', 'aria-label': 'frame' });
    this.play = h('button.play', { type: 'button', 'aria-pressed': 'false' }, 'Play');
    this.preset = h('select.preset', { 'aria-label': 'window preset' },
      Object.keys(PRESETS).map((k) => h('option', { value: k, selected: k === 'bone' }, k.replace('_', ' '))));
    this.label = h('span.muted');
    const what = p.type === 'rotating' ? 'rotating MIP' : p.type;
    this.el = h('figure.product', { dataset: { index: String(p.index), type: p.type } },
      h('figcaption', `${p.index}: ${what} · ${p.shape ? p.shape.join(' × ') : ''}`),
      this.stage, h('div.row', this.play, this.slider, this.label, this.preset));
    this.slider.addEventListener('input', () => this.show(Number(this.slider.value)));
    this.preset.addEventListener('change', () => this.show(this.frame));
    this.play.addEventListener('click', () => this.toggle());
  }

  async load(signal) {
    const buf = await bytes(`/v1/jobs/${this.job.id}/result/products/${this.p.index}?format=npy`, null, signal);
    const a = decode(buf);
    const s = a.shape.length === 2 ? [1, ...a.shape] : a.shape;
    this.n = s;
    this.data = a.data;
    this.slider.max = String(s[0] - 1);
    this.slider.hidden = s[0] < 2;
    this.play.hidden = s[0] < 2;
    this.label.hidden = s[0] < 2;
    const [rowMm, colMm] = this.p.pixel_mm || [1, 1];
    this.canvas.width = s[2];
    this.canvas.height = s[1];
    // CSS pixels per mm: at most 480 × 720 px on screen, and small images (a few cm) enlarged to about
    // 320 px along their longer side.
    const physH = s[1] * rowMm;
    const physW = s[2] * colMm;
    const scale = Math.min(480 / physH, 720 / physW, Math.max(1, 320 / Math.max(physW, physH)));
    this.canvas.style.width = `${Math.round(physW * scale)}px`;
    this.canvas.style.height = `${Math.round(physH * scale)}px`;
    // A rotation starts at its first angle (anterior), a series of planes at its middle plane.
    this.show(this.p.type === 'rotating' ? 0 : Math.floor((s[0] - 1) / 2));
  }

  show(f) {
    this.frame = f;
    const [, rows, cols] = this.n;
    const [wwHu, wlHu] = PRESETS[this.preset.value];
    const ww = this.hu ? wwHu : (MU_WATER * wwHu) / 1000;
    const wl = this.hu ? wlHu : MU_WATER * (1 + wlHu / 1000);
    const ctx = this.canvas.getContext('2d');
    const img = ctx.createImageData(cols, rows);
    const out = new Uint32Array(img.data.buffer);
    const src = this.data.subarray(f * rows * cols, (f + 1) * rows * cols);
    const lo = wl - ww / 2;
    for (let x = 0; x < src.length; x += 1) {
      let g = ((src[x] - lo) * 255) / ww;
      g = g < 0 ? 0 : g > 255 ? 255 : g | 0;
      out[x] = 0xff000000 | (g << 16) | (g << 8) | g;
    }
    ctx.putImageData(img, 0, 0);
    setOrientLabels(this.stage, this.p, f);
    this.el.dataset.frame = String(f);
    this.slider.value = String(f);
    this.label.textContent = `frame ${f + 1} / ${this.n[0]}`;
  }

  toggle() {
    if (this.timer) {
      clearInterval(this.timer);
      this.timer = 0;
    } else {
      this.timer = setInterval(() => this.show((this.frame + 1) % this.n[0]), 80);
    }
    this.el.dataset.playing = this.timer ? 'true' : 'false';
    this.play.textContent = this.timer ? 'Pause' : 'Play';
    this.play.setAttribute('aria-pressed', this.timer ? 'true' : 'false');
  }

  stop() {
    if (this.timer) clearInterval(this.timer);
  }
}

const RENDER_NAMES = { volume_render: 'volume rendering', surface_render: 'shaded surface display' };

/** The parameters of a rendering: its request (as the job records it, defaults filled) and the server's facts. */
function renderFacts(spec, p) {
  const s = spec || {};
  const cam = s.camera || {};
  const camera = [`${cam.view || 'anterior'} view`, `azimuth ${cam.azimuth_deg ?? 0}°`,
    `elevation ${cam.elevation_deg ?? 0}°`, `roll ${cam.roll_deg ?? 0}°`, `zoom ${cam.zoom ?? 1}`,
    cam.projection || 'orthographic'].join(', ');
  const surfaces = (s.surfaces || []).map((x) => `iso ${x.iso}${s.units === 'native' ? '' : ' HU'}`
    + `${x.opacity !== undefined && x.opacity !== 1 ? ` at opacity ${x.opacity}` : ''}`).join('; ');
  const clip = s.clip && (s.clip.planes || []).length ? `${s.clip.planes.length} plane(s)` : null;
  const rows = [
    ['Description', p.description],
    ['Preset', p.type === 'volume_render' ? (s.preset || (s.transfer_function ? 'custom transfer function' : 'bone')) : null],
    ['Surfaces', p.type === 'surface_render' ? surfaces : null],
    ['Camera', camera],
    ['Size', p.shape ? `${p.shape[2]} × ${p.shape[1]} px` : null],
    ['Pixel', p.pixel_mm ? `${fmtNum(p.pixel_mm[0], 3)} mm` : null],
    ['Frames', p.shape ? String(p.shape[0]) : null],
    ['Step', s.step_mm ? `${s.step_mm} mm` : null],
    ['Clip', clip],
  ].filter(([, v]) => v !== null && v !== undefined && v !== '');
  return h('dl.facts.render-facts', rows.map(([k, v]) => [h('dt', k), h('dd', { dataset: { fact: k.toLowerCase() } }, v)]));
}

/**
 * A volume_render or surface_render product: frame `k` as the server's PNG (`?format=png&frame=k`), a slider
 * over the frames of a rotation, and Play showing the server's animated PNG (`?format=apng`).
 */
class RenderView {
  constructor(job, p) {
    this.job = job;
    this.p = p;
    this.base = `/v1/jobs/${job.id}/result/products/${p.index}`;
    this.frames = p.shape ? p.shape[0] : 1;
    this.urls = new Map(); // frame -> object URL
    this.frame = 0;
    this.img = h('img.render-still', { alt: `${RENDER_NAMES[p.type]}, frame 1` });
    this.anim = h('img.render-apng', { alt: `${RENDER_NAMES[p.type]}, rotation`, hidden: true });
    this.stage = h('div.product-stage', this.img, this.anim, orientLabels(p, 0));
    this.slider = h('input.frame', {
      type: 'range', min: '0', max: String(this.frames - 1), value: '0', 'aria-label': 'frame',
    });
    this.play = h('button.play', { type: 'button', 'aria-pressed': 'false' }, 'Play rotation');
    this.label = h('span.muted.frame-label', `frame 1 / ${this.frames}`);
    const several = this.frames > 1;
    const spec = (job.products || [])[p.index];
    this.el = h('figure.product.render-product', { dataset: { index: String(p.index), type: p.type } },
      h('figcaption', `${p.index}: ${RENDER_NAMES[p.type] || p.type} · ${p.shape ? p.shape.join(' × ') : ''}`),
      this.stage, several ? h('div.row', this.play, this.slider, this.label) : null, renderFacts(spec, p));
    this.slider.addEventListener('input', () => this.show(Number(this.slider.value)).catch(() => {}));
    this.play.addEventListener('click', () => this.toggle().catch((e) => this.el.append(errorBox(e))));
  }

  async load(signal) {
    this.signal = signal;
    await this.show(0);
  }

  async show(k) {
    let url = this.urls.get(k);
    if (!url) {
      url = await blobUrl(`${this.base}?format=png&frame=${k}`, this.signal);
      this.urls.set(k, url);
    }
    await new Promise((resolve, reject) => {
      this.img.onload = resolve;
      this.img.onerror = () => reject(new Error(`frame ${k} of product ${this.p.index} is not an image`));
      this.img.src = url;
    });
    if (!this.img.style.width) {
      // Small renderings are shown enlarged (up to 4×, about 384 px wide), both pictures alike.
      const scale = Math.max(1, Math.min(4, 384 / this.img.naturalWidth));
      for (const el of [this.img, this.anim]) {
        el.style.width = `${Math.round(this.img.naturalWidth * scale)}px`;
        el.style.height = `${Math.round(this.img.naturalHeight * scale)}px`;
      }
    }
    this.frame = k;
    this.img.alt = `${RENDER_NAMES[this.p.type]}, frame ${k + 1}`;
    setOrientLabels(this.stage, this.p, k);
    this.el.dataset.frame = String(k);
    this.slider.value = String(k);
    this.label.textContent = `frame ${k + 1} / ${this.frames}`;
  }

  async toggle() {
    const playing = this.anim.hidden;
    if (playing && !this.animUrl) {
      this.animUrl = await blobUrl(`${this.base}?format=apng`, this.signal);
      this.anim.src = this.animUrl;
    }
    this.anim.hidden = !playing;
    this.img.hidden = playing;
    // The animation's frames face every way and give no event per frame: no letters while it plays.
    for (const el of this.stage.querySelectorAll('span.orient')) el.hidden = playing && (this.p.frame_orientations || []).length > 1;
    this.slider.disabled = playing;
    this.el.dataset.playing = playing ? 'true' : 'false';
    this.play.textContent = playing ? 'Stop' : 'Play rotation';
    this.play.setAttribute('aria-pressed', playing ? 'true' : 'false');
  }

  stop() {
    for (const u of this.urls.values()) URL.revokeObjectURL(u);
    this.urls.clear();
    if (this.animUrl) URL.revokeObjectURL(this.animUrl);
    this.animUrl = null;
  }
}

function meshCard(job, p, signal) {
  const m = p.mesh || {};
  const box = h('div.mesh-holder');
  const open = h('button.primary.mesh-open', { type: 'button' }, 'Open mesh in 3D');
  const el = h('figure.product.mesh-product', { dataset: { index: String(p.index), type: 'mesh' } },
    h('figcaption', `${p.index}: mesh`),
    h('dl.facts.mesh-facts',
      h('dt', 'Triangles'), h('dd.mesh-api-triangles', fmtNum(m.triangles, 0)),
      h('dt', 'Vertices'), h('dd', fmtNum(m.vertices, 0)),
      h('dt', 'Area'), h('dd.mesh-area', `${fmtNum(m.area_mm2, 1)} mm²`),
      h('dt', 'Enclosed volume'), h('dd.mesh-volume', `${fmtNum(m.volume_mm3, 1)} mm³ (${fmtNum(m.volume_mm3 / 1000, 1)} mL)`),
      h('dt', 'Closed / manifold'), h('dd', `${m.closed ? 'yes' : 'no'} / ${m.manifold ? 'yes' : 'no'}`)),
    (m.warnings || []).length
      ? h('ul.warnings', m.warnings.map((w) => h('li.warn', h('code', w.code), ' ', w.message)))
      : null,
    open, box);
  open.addEventListener('click', async () => {
    open.disabled = true;
    try {
      const { MeshView } = await import('./mesh.js');
      const view = new MeshView(box, `/v1/jobs/${job.id}/result/products/${p.index}`);
      signal.addEventListener('abort', () => view.destroy());
      await view.load(signal);
      open.hidden = true;
    } catch (e) {
      if (e.name !== 'AbortError') box.append(errorBox(e));
      open.disabled = false;
    }
  });
  return el;
}

export async function showProducts(root, job, signal) {
  const list = h('div.products');
  root.append(list);
  const stacks = [];
  for (const p of job.result.products) {
    if (p.type === 'mesh') {
      list.append(meshCard(job, p, signal));
    } else if (RENDER_NAMES[p.type]) {
      const v = new RenderView(job, p);
      list.append(v.el);
      stacks.push(v);
    } else {
      const v = new StackView(job, p);
      list.append(v.el);
      stacks.push(v);
    }
  }
  signal.addEventListener('abort', () => stacks.forEach((v) => v.stop()));
  await Promise.all(stacks.map((v) => v.load(signal).catch((e) => {
    if (e.name !== 'AbortError') clear(v.stage).append(errorBox(e));
  })));
}
