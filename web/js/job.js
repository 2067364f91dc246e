// A job's page: parameters, timings, attempts, error, metrics and warnings, live through its event stream;
// once it succeeded, its volume in the slice viewer, its products and meshes, and downloads.

import { api, download, follow } from './api.js';
import { clear, errorBox, fmtBytes, fmtDuration, fmtNum, fmtTime, h } from './dom.js';
import { progressBar, statusBadge } from './jobs.js';
import { showProducts } from './products.js';
import { SliceViewer } from './slices.js';

function dl(pairs) {
  return h('dl.facts', pairs.filter(([, v]) => v !== undefined && v !== null)
    .map(([k, v]) => [h('dt', k), h('dd', v)]));
}

function request(job) {
  const req = {};
  for (const k of ['input', 'algorithm', 'grid', 'outputs', 'steps', 'products']) {
    if (job[k] !== undefined && job[k] !== null) req[k] = job[k];
  }
  return h('pre.json#job-request', JSON.stringify(req, null, 2));
}

function errorPart(job) {
  if (!job.error) return null;
  return h('section.panel#job-error', h('h2', 'Error'),
    h('div.error', { role: 'alert' }, h('strong.error-title', job.error.title || 'Failed'), ' ',
      h('span.error-detail', job.error.detail || ''),
      job.error.code ? h('code.error-code', ` ${job.error.code}`) : null));
}

function metricsPart(job) {
  const m = job.result && job.result.metrics;
  if (!m) return null;
  return h('section.panel#job-metrics', h('h2', 'Metrics'),
    dl(Object.entries(m).map(([k, v]) => [k, typeof v === 'number' ? fmtNum(v, 4) : String(v)])));
}

function warningsPart(job) {
  const w = (job.result && job.result.warnings) || [];
  if (!w.length) return null;
  return h('section.panel', h('h2', 'Warnings'),
    h('ul.warnings', w.map((x) => h('li', h('code', x.code), ' ', x.message))));
}

function downloads(job) {
  const base = `/v1/jobs/${job.id}/result`;
  const short = job.id.slice(0, 8);
  const items = [[`${base}/volume.npy`, `${short}-volume.npy`, 'Volume (float32 .npy)']];
  if (job.kind === 'volume' || (job.result && job.result.frame)) {
    items.push([`${base}/series.zip`, `${short}-series.zip`, 'Derived CT series (DICOM ZIP)']);
  }
  for (const p of (job.result && job.result.products) || []) {
    const u = `${base}/products/${p.index}`;
    if (p.type === 'mesh') {
      items.push([u, `${short}-mesh-${p.index}.stl`, `Product ${p.index}: mesh (STL)`]);
      items.push([`${u}?format=dicom`, `${short}-mesh-${p.index}.dcm`, `Product ${p.index}: Encapsulated STL`]);
    } else if (p.type === 'volume_render' || p.type === 'surface_render') {
      const frames = p.shape ? p.shape[0] : 1;
      items.push([`${u}?format=png`, `${short}-${p.type}-${p.index}.png`, `Product ${p.index}: ${p.type} (PNG, first frame)`]);
      if (frames > 1) {
        items.push([`${u}?format=apng`, `${short}-${p.type}-${p.index}.apng`, `Product ${p.index}: ${p.type} (animated PNG, ${frames} frames)`]);
      }
      items.push([`${u}?format=npy`, `${short}-${p.type}-${p.index}.npy`, `Product ${p.index}: ${p.type} (uint8 RGB .npy)`]);
      items.push([`${u}?format=dicom`, `${short}-${p.type}-${p.index}.dcm`, `Product ${p.index}: ${p.type} (RGB Secondary Capture)`]);
    } else {
      items.push([`${u}?format=npy`, `${short}-${p.type}-${p.index}.npy`, `Product ${p.index}: ${p.type} (.npy)`]);
      items.push([`${u}?format=png`, `${short}-${p.type}-${p.index}.png`, `Product ${p.index}: ${p.type} (PNG)`]);
      items.push([`${u}?format=dicom`, `${short}-${p.type}-${p.index}.dcm`, `Product ${p.index}: ${p.type} (DICOM)`]);
    }
  }
  const msg = h('div.msg');
  return h('section.panel#downloads', h('h2', 'Downloads'), msg,
    h('ul.downloads', items.map(([url, name, label]) => h('li', h('button.link', {
      type: 'button',
      dataset: { url },
      onclick: () => download(url, name).catch((e) => clear(msg).append(errorBox(e))),
    }, label)))));
}

function summary(job) {
  const r = job.result || {};
  return h('section.panel#job-summary',
    h('div.row', h('h1', `Job ${job.id.slice(0, 8)}`), h('span#job-status', statusBadge(job.status)),
      h('span#job-progress', progressBar(job.progress)), h('span#job-stage.muted', job.stage || '')),
    h('details.job-facts', { open: job.status !== 'succeeded' },
      h('summary', `Timings, attempts and parameters · ran for ${fmtDuration(job.started_at, job.finished_at)}`),
      dl([
        ['Id', h('code', job.id)],
        ['Kind', job.kind],
        ['Input', job.input ? h('code', job.input) : undefined],
        ['Created', fmtTime(job.created_at)],
        ['Started', fmtTime(job.started_at)],
        ['Finished', fmtTime(job.finished_at)],
        ['Queued for', fmtDuration(job.created_at, job.started_at)],
        ['Ran for', fmtDuration(job.started_at, job.finished_at)],
        ['Attempts', String(job.attempts ?? '–')],
        ['Memory estimate', job.estimate_bytes ? fmtBytes(job.estimate_bytes) : undefined],
        ['Result shape', r.shape ? r.shape.join(' × ') : undefined],
        ['Units', r.units],
        ['Range', r.min !== undefined ? `${fmtNum(r.min, 4)} … ${fmtNum(r.max, 4)} (mean ${fmtNum(r.mean, 4)})` : undefined],
      ]),
      request(job)));
}

export async function showJob(main, id, signal) {
  let job = await api(`/v1/jobs/${id}`, { signal });
  const head = h('div');
  const rest = h('div');
  main.append(head, rest);
  const actions = h('div.row.actions');
  let shown = null; // the status the page was built for
  const render = () => {
    if (shown === job.status) {
      // Progress within the same status: update in place, so the buttons keep focus and the open details stay.
      clear(head.querySelector('#job-progress')).append(progressBar(job.progress));
      head.querySelector('#job-stage').textContent = job.stage || '';
      return;
    }
    shown = job.status;
    clear(head).append(...[summary(job), actions, errorPart(job), metricsPart(job), warningsPart(job)].filter(Boolean));
    clear(actions);
    const msg = h('div.msg');
    if (job.status === 'queued' || job.status === 'running') {
      actions.append(h('button#job-cancel', { type: 'button', onclick: () =>
        api(`/v1/jobs/${id}/cancel`, { method: 'POST' }).catch((e) => msg.append(errorBox(e))) }, 'Cancel'));
    } else {
      actions.append(h('button#job-delete', { type: 'button', onclick: () =>
        api(`/v1/jobs/${id}`, { method: 'DELETE' }).then(() => { location.hash = '#/jobs'; })
          .catch((e) => msg.append(errorBox(e))) }, 'Delete'));
    }
    actions.append(msg);
  };
  render();
  if (job.status === 'queued' || job.status === 'running') {
    await follow(`/v1/jobs/${id}/events`, (name, data) => {
      if (name === 'final') job = data;
      else Object.assign(job, data);
      render();
    }, signal);
    job = await api(`/v1/jobs/${id}`, { signal });
    shown = null;
    render();
  }
  if (job.status !== 'succeeded' || !job.result) return;
  const r = job.result;
  const viewer = h('section.panel#slice-panel', h('h2', 'Slices'));
  rest.append(viewer);
  const sv = new SliceViewer(viewer, {
    url: `/v1/jobs/${id}/result/volume.npy`,
    shape: r.shape,
    frame: r.frame || null,
    units: r.units || 'mu_per_mm',
    grid: job.grid || null,
  });
  signal.addEventListener('abort', () => sv.destroy());
  await sv.start(signal);
  if ((r.products || []).length) {
    const prods = h('section.panel#products', h('h2', 'Products'));
    rest.append(prods);
    await showProducts(prods, job, signal);
  }
  rest.append(downloads(job));
}
