// Small DOM helpers: element building, number and time formatting, the error banner.

/** h('div.cls#id', {attrs}, children...) */
export function h(tag, attrs, ...children) {
  const m = /^([a-z0-9]+)((?:[.#][\w-]+)*)$/i.exec(tag);
  const el = document.createElement(m ? m[1] : tag);
  if (m && m[2]) {
    for (const part of m[2].match(/[.#][\w-]+/g)) {
      if (part[0] === '.') el.classList.add(part.slice(1));
      else el.id = part.slice(1);
    }
  }
  if (attrs && (typeof attrs !== 'object' || attrs instanceof Node || Array.isArray(attrs))) {
    children.unshift(attrs);
    attrs = null;
  }
  for (const [k, v] of Object.entries(attrs || {})) {
    if (v === undefined || v === null || v === false) continue;
    if (k.startsWith('on')) el.addEventListener(k.slice(2), v);
    else if (k === 'dataset') Object.assign(el.dataset, v);
    else if (v === true) el.setAttribute(k, '');
    else el.setAttribute(k, v);
  }
  for (const c of children.flat(Infinity)) {
    if (c === null || c === undefined || c === false) continue;
    el.append(c instanceof Node ? c : String(c));
  }
  return el;
}

export function clear(el) {
  while (el.firstChild) el.firstChild.remove();
  return el;
}

export function fmtBytes(n) {
  if (!Number.isFinite(n)) return '–';
  const u = ['B', 'KiB', 'MiB', 'GiB'];
  let i = 0;
  while (n >= 1024 && i < u.length - 1) {
    n /= 1024;
    i += 1;
  }
  return `${n.toFixed(i ? 1 : 0)} ${u[i]}`;
}

export function fmtTime(iso) {
  if (!iso) return '–';
  const d = new Date(iso);
  return Number.isNaN(d.getTime()) ? iso : d.toLocaleString();
}

export function fmtDuration(a, b) {
  if (!a || !b) return '–';
  const s = (new Date(b) - new Date(a)) / 1000;
  return s < 60 ? `${s.toFixed(1)} s` : `${Math.floor(s / 60)} min ${Math.round(s % 60)} s`;
}

export function fmtNum(x, digits = 1) {
  if (typeof x !== 'number' || !Number.isFinite(x)) return '–';
  return x.toLocaleString('en-US', { maximumFractionDigits: digits });
}

/** A readable block for an ApiError or any error. */
export function errorBox(e) {
  const title = (e && e.title) || 'Error';
  const detail = (e && (e.detail || e.message)) || String(e);
  const attrs = { role: 'alert' };
  if (e && e.pointer) attrs.dataset = { pointer: e.pointer };
  return h('div.error', attrs, h('strong.error-title', title), ' ',
    h('span.error-detail', detail), e && e.code ? h('code.error-code', ` ${e.code}`) : null);
}

/** Show or hide the page-wide banner. */
export function banner(e) {
  const el = document.getElementById('banner');
  if (!el) return;
  clear(el);
  if (e) {
    el.append(errorBox(e));
    el.hidden = false;
  } else {
    el.hidden = true;
  }
}
