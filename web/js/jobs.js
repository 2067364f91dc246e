// The jobs list: filters by status and kind, live creation, status, progress and deletion of every job
// through one stream (`GET /v1/events`), cancel and delete.

import { api, follow } from './api.js';
import { clear, errorBox, fmtTime, h } from './dom.js';

const STATUSES = ['queued', 'running', 'succeeded', 'failed', 'canceled'];
const TERMINAL = new Set(['succeeded', 'failed', 'canceled']);

export function statusBadge(status) {
  return h(`span.status.status-${status}`, { dataset: { status } }, status);
}

export function progressBar(p) {
  const bar = h('progress', { max: '100', value: String(p || 0), 'aria-label': 'progress' });
  return h('span.progress', bar, h('span.pct', `${p || 0} %`));
}

function row(job, actions) {
  const tr = h('tr', { dataset: { id: job.id } },
    h('td', h('a', { href: `#/job/${job.id}` }, job.id.slice(0, 8))),
    h('td', job.kind),
    h('td.cell-status', statusBadge(job.status)),
    h('td.cell-progress', progressBar(job.progress)),
    h('td.cell-stage', job.stage || ''),
    h('td', fmtTime(job.created_at)),
    h('td.actions', actions(job)));
  return tr;
}

function update(tr, ev) {
  const s = tr.querySelector('.cell-status');
  clear(s).append(statusBadge(ev.status));
  clear(tr.querySelector('.cell-progress')).append(progressBar(ev.progress));
  tr.querySelector('.cell-stage').textContent = ev.stage || '';
}

export async function showJobs(main, signal) {
  const params = new URLSearchParams(location.hash.split('?')[1] || '');
  const status = h('select#filter-status', { 'aria-label': 'status' },
    h('option', { value: '' }, 'any status'),
    STATUSES.map((s) => h('option', { value: s, selected: params.get('status') === s }, s)));
  const kind = h('select#filter-kind', { 'aria-label': 'kind' },
    h('option', { value: '' }, 'any kind'),
    ['reconstruction', 'volume'].map((k) => h('option', { value: k, selected: params.get('kind') === k }, k)));
  const body = h('tbody');
  const more = h('button', { type: 'button', hidden: true }, 'More');
  const msg = h('div.msg');
  const table = h('table.jobs#jobs-table',
    h('thead', h('tr', ['Job', 'Kind', 'Status', 'Progress', 'Stage', 'Created', ''].map((t) => h('th', t)))),
    body);
  main.append(h('section.panel',
    h('div.row', h('h1', 'Jobs'), h('div.filters', status, kind,
      h('a.button', { href: '#/send' }, 'Send work'))),
    msg, h('div.scroll', table), more));

  // Never an empty table: "Loading jobs…" until the first page is in, then the jobs, "No jobs yet" (with
  // the way to start one) or, when filtered, "No jobs match"; an error row when they cannot be loaded.
  const stateRow = (cls, ...content) => h(`tr.${cls}`, h('td', { colspan: '7' }, ...content));
  const emptyRow = () => (status.value || kind.value
    ? stateRow('empty', 'No jobs match these filters.')
    : stateRow('empty', 'No jobs yet. ', h('a', { href: '#/send' }, 'Send work'),
      ' to start one: a DICOM series, or a sinogram with its geometry.'));
  body.append(stateRow('loading', h('span.spinner', { 'aria-hidden': 'true' }), 'Loading jobs…'));

  let cursor = null;
  const actions = (job) => {
    if (!TERMINAL.has(job.status)) {
      return h('button.cancel', { type: 'button', onclick: () => act(job, 'cancel') }, 'Cancel');
    }
    return h('button.delete', { type: 'button', onclick: () => act(job, 'delete') }, 'Delete');
  };
  const act = async (job, what) => {
    clear(msg);
    try {
      if (what === 'cancel') await api(`/v1/jobs/${job.id}/cancel`, { method: 'POST' });
      else {
        await api(`/v1/jobs/${job.id}`, { method: 'DELETE' });
        const tr = body.querySelector(`tr[data-id="${job.id}"]`);
        if (tr) tr.remove();
      }
    } catch (e) {
      msg.append(errorBox(e));
    }
  };
  let generation = 0; // a newer filter makes the answers of older requests stale
  const load = async (reset) => {
    if (reset) {
      generation += 1;
      cursor = null;
      clear(body);
    }
    const mine = generation;
    const q = new URLSearchParams({ limit: '50' });
    if (status.value) q.set('status', status.value);
    if (kind.value) q.set('kind', kind.value);
    if (cursor) q.set('cursor', cursor);
    const page = await api(`/v1/jobs?${q}`, { signal });
    if (mine !== generation) return;
    for (const job of page.jobs) {
      if (!body.querySelector(`tr[data-id="${job.id}"]`)) body.append(row(job, actions));
    }
    if (!body.children.length) body.append(emptyRow());
    cursor = page.next_cursor;
    more.hidden = !cursor;
  };
  const refilter = () => {
    const q = new URLSearchParams();
    if (status.value) q.set('status', status.value);
    if (kind.value) q.set('kind', kind.value);
    history.replaceState(null, '', `#/jobs${q.toString() ? `?${q}` : ''}`);
    load(true).catch((e) => msg.append(errorBox(e)));
  };
  status.addEventListener('change', refilter);
  kind.addEventListener('change', refilter);
  more.addEventListener('click', () => load(false).catch((e) => msg.append(errorBox(e))));

  // Every job's events on one connection. The list is loaded once the stream is `ready`, so no event falls
  // between the two; a dropped stream resumes after the last event it delivered (`Last-Event-ID`), and
  // `resync` (events lost) reloads the list.
  const rowOf = (id) => body.querySelector(`tr[data-id="${id}"]`);
  const shown = (job) => (!status.value || status.value === job.status) && (!kind.value || kind.value === job.kind);
  const apply = (name, data) => {
    if (!data || typeof data !== 'object') return;
    if (name === 'created') {
      if (rowOf(data.id) || !shown(data)) return;
      const empty = body.querySelector('tr.empty');
      if (empty) empty.remove();
      body.prepend(row(data, actions));
    } else if (name === 'status' || name === 'progress') {
      const tr = rowOf(data.id);
      if (!tr) return;
      update(tr, data);
      if (name === 'status') clear(tr.querySelector('.actions')).append(actions(data));
    } else if (name === 'deleted') {
      const tr = rowOf(data.id);
      if (tr) tr.remove();
    } else if (name === 'resync') {
      load(true).catch((e) => msg.append(errorBox(e)));
    }
  };
  let lastId = null;
  let started = false;
  let ready;
  const first = new Promise((resolve, reject) => {
    ready = { resolve, reject };
  });
  const run = async () => {
    while (!signal.aborted) {
      try {
        await follow('/v1/events', (name, data, id) => {
          if (id) lastId = id;
          if (name !== 'ready') apply(name, data);
          else if (!started) {
            started = true;
            ready.resolve();
          } else load(true).catch((e) => msg.append(errorBox(e)));
        }, signal, lastId);
      } catch (e) {
        if (signal.aborted) return;
        ready.reject(e);
        if (e.status === 401) return;
      }
      await new Promise((r) => { setTimeout(r, 1000); });
    }
  };
  run();
  try {
    await first;
    await load(true);
  } catch (e) {
    if (e.name !== 'AbortError') {
      clear(body).append(stateRow('error', `Could not load the jobs: ${e.title || e.message}.`));
    }
    throw e;
  }
}
