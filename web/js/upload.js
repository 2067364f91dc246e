// The DICOM drop zone: files, a folder or a ZIP, by drop or by the file inputs; uploaded with progress to
// `POST /v1/series` (one multipart part per file, or the ZIP as application/zip); then the assembly report:
// every series (ready or refused, with its warnings) and every refused file.

import { upload } from './api.js';
import { clear, errorBox, fmtBytes, h } from './dom.js';

/** Every file under a dropped entry (folders walked). */
async function entryFiles(entry, out) {
  if (entry.isFile) {
    out.push(await new Promise((res, rej) => entry.file(res, rej)));
  } else if (entry.isDirectory) {
    const reader = entry.createReader();
    for (;;) {
      const batch = await new Promise((res, rej) => reader.readEntries(res, rej));
      if (!batch.length) break;
      for (const e of batch) await entryFiles(e, out);
    }
  }
}

function seriesReport(s, onSeries) {
  const se = s.series || {};
  const rep = s.report || {};
  const slices = se.shape ? se.shape[0] : rep.instances;
  const warnings = [...(se.warnings || []), ...(rep.warnings || [])];
  const seen = new Set();
  const uniq = warnings.filter((w) => {
    const key = `${w.code}:${w.message}`;
    if (seen.has(key)) return false;
    seen.add(key);
    return true;
  });
  return h(`li.series.series-${s.status}`, { dataset: { status: s.status, id: se.id || '', slices: String(slices ?? '') } },
    h('strong', s.status === 'ready' ? 'Ready' : 'Refused'), ' · ',
    h('span.slices', `${slices ?? '?'} slices`),
    se.shape ? ` · ${se.shape.join(' × ')} voxels` : '',
    se.frame ? ` · spacing ${se.frame.spacing_mm.map((x) => +x.toFixed(3)).join(' × ')} mm` : '',
    se.description ? ` · ${se.description}` : '',
    s.error ? errorBox(s.error) : null,
    uniq.length ? h('ul.warnings', uniq.map((w) => h('li.warn', h('code', w.code), ' ', w.message))) : null,
    s.status === 'ready' && onSeries ? onSeries(se) : null);
}

/** The assembly report of a `POST /v1/series` answer. */
export function report(answer, onSeries) {
  const series = answer.series || [];
  const rejected = answer.rejected || [];
  return h('div#upload-report',
    h('h3', `${series.length} series`),
    h('ul.series-list', series.map((s) => seriesReport(s, onSeries))),
    rejected.length ? [h('h3', `${rejected.length} refused files`),
      h('ul.rejected', rejected.map((r) => h('li', h('code', r.file), ' ', h('code', r.code), ' ', r.detail)))] : null);
}

/** The drop zone; `onSeries(series)` returns what to show beside each ready series. */
export function dropZone(onSeries) {
  const files = h('input#dicom-files', { type: 'file', multiple: true, accept: '.dcm,.zip,application/dicom,application/zip' });
  const folder = h('input#dicom-folder', { type: 'file', webkitdirectory: true });
  const progress = h('progress#upload-progress', { max: '100', value: '0', hidden: true });
  const status = h('span#upload-status.muted');
  const out = h('div#upload-result');
  const zone = h('div.dropzone#dropzone', { tabindex: '0', role: 'region', 'aria-label': 'DICOM drop zone' },
    h('p', 'Drop DICOM files, a folder or a ZIP here, or choose: '),
    h('label.button', 'Files or ZIP…', files), ' ', h('label.button', 'Folder…', folder),
    h('p', progress, ' ', status));
  for (const input of [files, folder]) input.classList.add('visually-hidden');

  const send = async (list) => {
    list = list.filter((f) => f.size > 0 && !f.name.startsWith('.'));
    if (!list.length) return;
    clear(out);
    const total = list.reduce((a, f) => a + f.size, 0);
    let body;
    let type = null;
    if (list.length === 1 && /\.zip$/i.test(list[0].name)) {
      body = list[0];
      type = 'application/zip';
    } else {
      body = new FormData();
      for (const f of list) body.append('file', f, f.webkitRelativePath || f.name);
    }
    progress.hidden = false;
    progress.value = 0;
    status.textContent = `uploading ${list.length} file${list.length > 1 ? 's' : ''} (${fmtBytes(total)})…`;
    try {
      const answer = await upload('/v1/series', body, type, (done, all) => {
        progress.value = all ? Math.round((100 * done) / all) : 0;
        if (all && done >= all) status.textContent = 'assembling the series…';
      });
      progress.value = 100;
      status.textContent = 'done';
      out.append(report(answer, onSeries));
    } catch (e) {
      status.textContent = '';
      out.append(errorBox(e));
    }
  };
  files.addEventListener('change', () => send([...files.files]));
  folder.addEventListener('change', () => send([...folder.files]));
  zone.addEventListener('dragover', (ev) => {
    ev.preventDefault();
    zone.classList.add('over');
  });
  zone.addEventListener('dragleave', () => zone.classList.remove('over'));
  zone.addEventListener('drop', async (ev) => {
    ev.preventDefault();
    zone.classList.remove('over');
    const list = [];
    const entries = [...ev.dataTransfer.items].map((i) => i.webkitGetAsEntry && i.webkitGetAsEntry()).filter(Boolean);
    if (entries.length) for (const e of entries) await entryFiles(e, list);
    else list.push(...ev.dataTransfer.files);
    send(list);
  });
  zone.addEventListener('keydown', (ev) => {
    if (ev.key === 'Enter' || ev.key === ' ') {
      ev.preventDefault();
      files.click();
    }
  });
  return h('div', zone, out);
}
