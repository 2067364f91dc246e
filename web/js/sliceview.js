// One plane of the slice viewer: a canvas at the image's own resolution, windowed in the browser, with
// orientation labels, a scale bar, linked crosshairs, the value and position under the cursor, wheel and key
// scrolling (one slice per wheel event, i.e. per notch of a mouse wheel) and window/level by right-drag.

import { h } from './dom.js';
import { planeSides } from './orient.js';

/**
 * Planes in display orientation (DESIGN §2, radiological): columns and rows of the screen image as voxel
 * axes. `flip` reverses the row axis (superior up). With a patient, the side labels come from the volume's
 * direction vectors (orient.js: "A" for an axis-aligned series, combined such as "AI" for a tilted one);
 * without one, the array axes.
 */
export const PLANES = {
  axial: { fixed: 'k', col: 'i', row: 'j', flip: false, plain: ['−y', '+y', '−x', '+x'] },
  coronal: { fixed: 'j', col: 'i', row: 'k', flip: true, plain: ['+z', '−z', '−x', '+x'] },
  sagittal: { fixed: 'i', col: 'j', row: 'k', flip: true, plain: ['+z', '−z', '−y', '+y'] },
};

const AXIS_ALIGNED = [[1, 0, 0], [0, 1, 0], [0, 0, 1]];

const SCALE_STEPS = [1, 2, 5, 10, 20, 25, 50, 100, 200, 500];

export class PlaneView {
  /** vol: the shared volume state (see slices.js); name: axial | coronal | sagittal. */
  constructor(vol, name) {
    this.vol = vol;
    this.name = name;
    this.p = PLANES[name];
    this.draws = 0;
    const [top, bottom, left, right] = vol.patient
      ? planeSides(name, (vol.opts.frame && vol.opts.frame.direction) || AXIS_ALIGNED)
      : this.p.plain;
    this.canvas = h('canvas.image', { 'aria-hidden': 'true' });
    this.overlay = h('canvas.overlay', { 'aria-hidden': 'true' });
    this.bar = h('div.scalebar', h('span.scalebar-line'), h('span.scalebar-text'));
    this.title = h('span.view-title');
    this.readout = h('output.readout', { 'aria-live': 'off' }, '\u00a0');
    this.stage = h('div.stage', this.canvas, this.overlay,
      h('span.orient.orient-top', { dataset: { side: 'top' } }, top),
      h('span.orient.orient-bottom', { dataset: { side: 'bottom' } }, bottom),
      h('span.orient.orient-left', { dataset: { side: 'left' } }, left),
      h('span.orient.orient-right', { dataset: { side: 'right' } }, right),
      this.bar);
    this.el = h(`div.view.view-${name}`, {
      tabindex: '0', role: 'group', 'aria-label': `${name} view: arrow keys or wheel scroll, right-drag sets the window`,
      dataset: { plane: name },
    }, h('div.view-head', this.title), this.stage, this.readout);
    this.bind();
  }

  /** Image size on screen: [columns, rows] and mm per column and row. */
  dims() {
    const { n, spacing } = this.vol;
    const ax = { i: 0, j: 1, k: 2 };
    return {
      w: n[ax[this.p.col]], hgt: n[ax[this.p.row]],
      mmCol: spacing[ax[this.p.col]], mmRow: spacing[ax[this.p.row]],
    };
  }

  /** The index along this plane's normal and its count. */
  index() {
    const ax = { i: 0, j: 1, k: 2 };
    return [this.vol.cursor[ax[this.p.fixed]], this.vol.n[ax[this.p.fixed]]];
  }

  /** Voxel [i, j, k] of screen image pixel (c, r). */
  voxel(c, r) {
    const { hgt } = this.dims();
    const v = [...this.vol.cursor];
    const ax = { i: 0, j: 1, k: 2 };
    v[ax[this.p.col]] = c;
    v[ax[this.p.row]] = this.p.flip ? hgt - 1 - r : r;
    return v;
  }

  /** Fit the canvas to `box` CSS pixels keeping the physical aspect ratio. */
  layout(boxW, boxH) {
    const { w, hgt, mmCol, mmRow } = this.dims();
    const physW = w * mmCol;
    const physH = hgt * mmRow;
    const s = Math.max(0.01, Math.min(boxW / physW, boxH / physH));
    this.cssW = Math.max(1, Math.floor(physW * s));
    this.cssH = Math.max(1, Math.floor(physH * s));
    this.mmPerCss = 1 / s;
    for (const c of [this.canvas, this.overlay]) {
      c.style.width = `${this.cssW}px`;
      c.style.height = `${this.cssH}px`;
    }
    this.stage.style.width = `${this.cssW}px`;
    this.stage.style.height = `${this.cssH}px`;
    this.overlay.width = this.cssW;
    this.overlay.height = this.cssH;
    this.scaleBar();
  }

  scaleBar() {
    const target = this.mmPerCss * this.cssW * 0.25;
    let mm = SCALE_STEPS[0];
    for (const s of SCALE_STEPS) if (s <= target) mm = s;
    this.bar.querySelector('.scalebar-line').style.width = `${Math.round(mm / this.mmPerCss)}px`;
    this.bar.querySelector('.scalebar-text').textContent = this.vol.spacingKnown ? `${mm} mm` : `${mm} px`;
    this.bar.dataset.mm = String(mm);
  }

  /** Draw the current slice with the current window (no request: the data is in the browser). */
  draw() {
    const { w, hgt } = this.dims();
    const data = this.vol.sliceData(this.name);
    const [idx, count] = this.index();
    this.title.textContent = `${this.name[0].toUpperCase()}${this.name.slice(1)} slice ${idx} (0–${count - 1})`;
    this.el.dataset.index = String(idx);
    if (!data) {
      this.el.classList.add('pending');
      return;
    }
    this.el.classList.remove('pending');
    if (this.canvas.width !== w || this.canvas.height !== hgt) {
      this.canvas.width = w;
      this.canvas.height = hgt;
    }
    const ctx = this.canvas.getContext('2d');
    const img = ctx.createImageData(w, hgt);
    const out = new Uint32Array(img.data.buffer);
    const { ww, wl } = this.vol.window;
    const lo = wl - ww / 2;
    const k = 255 / Math.max(ww, 1e-12);
    for (let r = 0; r < hgt; r += 1) {
      const src = (this.p.flip ? hgt - 1 - r : r) * w;
      const dst = r * w;
      for (let c = 0; c < w; c += 1) {
        let g = (data[src + c] - lo) * k;
        g = g < 0 ? 0 : g > 255 ? 255 : g | 0;
        out[dst + c] = 0xff000000 | (g << 16) | (g << 8) | g;
      }
    }
    ctx.putImageData(img, 0, 0);
    this.draws += 1;
    this.el.dataset.draws = String(this.draws);
    this.cross();
  }

  /** Linked crosshairs: the cursor's position in the other two planes. */
  cross() {
    const ctx = this.overlay.getContext('2d');
    ctx.clearRect(0, 0, this.overlay.width, this.overlay.height);
    const { w, hgt } = this.dims();
    const ax = { i: 0, j: 1, k: 2 };
    const c = this.vol.cursor[ax[this.p.col]];
    let r = this.vol.cursor[ax[this.p.row]];
    if (this.p.flip) r = hgt - 1 - r;
    const x = ((c + 0.5) / w) * this.cssW;
    const y = ((r + 0.5) / hgt) * this.cssH;
    ctx.strokeStyle = 'rgba(255, 200, 0, 0.7)';
    ctx.lineWidth = 1;
    ctx.setLineDash([4, 4]);
    ctx.beginPath();
    ctx.moveTo(Math.round(x) + 0.5, 0);
    ctx.lineTo(Math.round(x) + 0.5, this.cssH);
    ctx.moveTo(0, Math.round(y) + 0.5);
    ctx.lineTo(this.cssW, Math.round(y) + 0.5);
    ctx.stroke();
  }

  /** Screen image pixel under a pointer event, or null outside. */
  pixelAt(ev) {
    const rect = this.canvas.getBoundingClientRect();
    const { w, hgt } = this.dims();
    const c = Math.floor(((ev.clientX - rect.left) / rect.width) * w);
    const r = Math.floor(((ev.clientY - rect.top) / rect.height) * hgt);
    return c >= 0 && r >= 0 && c < w && r < hgt ? [c, r] : null;
  }

  showValue(ev) {
    const px = this.pixelAt(ev);
    if (!px) return;
    const v = this.voxel(px[0], px[1]);
    const value = this.vol.valueAt(v);
    const pos = this.vol.position(v);
    const ro = this.readout;
    ro.dataset.i = String(v[0]);
    ro.dataset.j = String(v[1]);
    ro.dataset.k = String(v[2]);
    ro.dataset.value = value === null ? '' : String(value);
    ro.dataset.positionMm = pos.join(',');
    const unit = this.vol.units === 'hu' ? 'HU' : this.vol.units === 'mu_per_mm' ? '/mm' : '';
    const shown = value === null ? '…' : this.vol.units === 'hu' ? value.toFixed(0) : value.toPrecision(4);
    const where = pos.map((x) => x.toFixed(1)).join(', ');
    ro.textContent = `${shown} ${unit} · ${this.vol.patient ? 'LPS' : 'xyz'} (${where}) mm · voxel [${v.join(', ')}]`;
  }

  bind() {
    const el = this.el;
    el.addEventListener('wheel', (ev) => {
      ev.preventDefault();
      this.vol.step(this.name, ev.deltaY > 0 ? -1 : 1);
    }, { passive: false });
    el.addEventListener('keydown', (ev) => {
      const [idx, count] = this.index();
      const moves = { ArrowUp: 1, ArrowRight: 1, ArrowDown: -1, ArrowLeft: -1, PageUp: 10, PageDown: -10 };
      if (ev.key in moves) this.vol.step(this.name, moves[ev.key]);
      else if (ev.key === 'Home') this.vol.step(this.name, -idx);
      else if (ev.key === 'End') this.vol.step(this.name, count - 1 - idx);
      else return;
      ev.preventDefault();
    });
    el.addEventListener('contextmenu', (ev) => ev.preventDefault());
    let drag = null;
    this.stage.addEventListener('pointerdown', (ev) => {
      el.focus({ preventScroll: true });
      if (ev.button === 2) {
        drag = { x: ev.clientX, y: ev.clientY, ...this.vol.window };
        this.stage.setPointerCapture(ev.pointerId);
      } else if (ev.button === 0) {
        const px = this.pixelAt(ev);
        if (px) this.vol.moveCursor(this.voxel(px[0], px[1]));
      }
    });
    this.stage.addEventListener('pointermove', (ev) => {
      if (drag) {
        const scale = this.vol.windowScale();
        this.vol.setWindow(Math.max(scale / 100, drag.ww + (ev.clientX - drag.x) * scale / 100),
          drag.wl - (ev.clientY - drag.y) * scale / 100);
      }
      this.showValue(ev);
    });
    const end = () => { drag = null; };
    this.stage.addEventListener('pointerup', end);
    this.stage.addEventListener('pointercancel', end);
  }
}
