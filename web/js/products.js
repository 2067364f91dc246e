// A volume job's products: image stacks (projections, MIP/MinIP, thick slabs, MPR and curved planes,
// rotating MIPs) fetched once as float32 .npy and windowed in the browser, stepped frame by frame or played
// as a loop; meshes open in the WebGL view (mesh.js, loaded on demand).

import { bytes } from './api.js';
import { clear, errorBox, fmtNum, h } from './dom.js';
import { decode } from './npy.js';
import { PRESETS } from './slices.js';

const MU_WATER = 0.0192;

class StackView {
  constructor(job, p) {
    this.job = job;
    this.p = p;
    this.hu = (job.result.units || 'hu') === 'hu';
    this.frame = 0;
    this.canvas = h('canvas.product-image');
    const o = p.orientation || {};
    this.stage = h('div.product-stage', this.canvas,
      ['top', 'bottom', 'left', 'right'].map((s) => h(`span.orient.orient-${s}`, { dataset: { side: s } }, o[s] || '')));
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
    const scale = Math.min(1, 480 / (s[1] * rowMm), 720 / (s[2] * colMm));
    this.canvas.style.width = `${Math.round(s[2] * colMm * scale * 1.0)}px`;
    this.canvas.style.height = `${Math.round(s[1] * rowMm * scale)}px`;
    this.show(0);
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
    this.play.textContent = this.timer ? 'Pause' : 'Play';
    this.play.setAttribute('aria-pressed', this.timer ? 'true' : 'false');
  }

  stop() {
    if (this.timer) clearInterval(this.timer);
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
      h('dt', 'Area'), h('dd', `${fmtNum(m.area_mm2, 1)} mm²`),
      h('dt', 'Enclosed volume'), h('dd', `${fmtNum(m.volume_mm3, 1)} mm³ (${fmtNum(m.volume_mm3 / 1000, 1)} mL)`),
      h('dt', 'Closed / manifold'), h('dd', `${m.closed ? 'yes' : 'no'} / ${m.manifold ? 'yes' : 'no'}`)),
    (m.warnings || []).length ? h('ul.warnings', m.warnings.map((w) => h('li.warn', w))) : null,
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
