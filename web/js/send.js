// Sending work: DICOM upload with its report, a volume protocol for a ready series, and a phantom simulated
// and reconstructed. Also the page of one series (its facts, slices and the protocol form).

import { api, limits, protocols } from './api.js';
import { clear, errorBox, fmtNum, h } from './dom.js';
import {
  ALGORITHMS_2D, ALGORITHMS_3D, PHANTOM_FIELDS, fieldOfPointer, limitAt, phantomRequests,
} from './protocols.js';
import { SliceViewer } from './slices.js';
import { dropZone } from './upload.js';

/**
 * The volume protocol form for a series (or a succeeded job) id: the server's protocols (the ones its rules
 * run) as presets, their steps and products editable as JSON. The form is `data-ready` once they arrived.
 */
export function protocolForm(input) {
  const preset = h('select.protocol-preset', { 'aria-label': 'protocol', disabled: true },
    h('option', { value: '' }, 'loading the protocols…'));
  const text = h('textarea.protocol-json', { 'aria-label': 'steps and products (JSON)', spellcheck: 'false' });
  const err = h('div.field-error', { role: 'alert' });
  const submit = h('button.primary.protocol-run', { type: 'submit', disabled: true }, 'Run protocol');
  const form = h('form.protocol', { dataset: { input } },
    h('div.row', h('label', 'Protocol ', preset), submit),
    h('details', h('summary', 'Steps and products (editable)'), text), err);
  let byName = new Map();
  const fill = () => {
    const p = byName.get(preset.value);
    if (p) text.value = JSON.stringify({ steps: p.steps, products: p.products }, null, 2);
  };
  preset.addEventListener('change', fill);
  protocols().then((list) => {
    byName = new Map(list.map((p) => [p.name, p]));
    clear(preset).append(...list.map((p) => h('option', { value: p.name }, p.description)));
    preset.disabled = false;
    submit.disabled = false;
    fill();
    form.dataset.ready = 'true';
  }).catch((e) => err.append(errorBox(e)));
  form.addEventListener('submit', async (ev) => {
    ev.preventDefault();
    clear(err);
    let body;
    try {
      body = JSON.parse(text.value);
    } catch (e) {
      err.textContent = `Not valid JSON: ${e.message}`;
      return;
    }
    submit.disabled = true;
    try {
      const job = await api('/v1/jobs', { method: 'POST', body: { kind: 'volume', input, ...body } });
      location.hash = `#/job/${job.id}`;
    } catch (e) {
      err.append(errorBox(e));
    } finally {
      submit.disabled = false;
    }
  });
  return form;
}

function seriesActions(series) {
  return h('div.series-actions', h('a.button', { href: `#/series/${series.id}` }, 'View slices'),
    protocolForm(series.id));
}

/**
 * The phantom form: simulate, then reconstruct. Maximums are the server's (`GET /v1/limits`); each field
 * the server's problem names by JSON Pointer gets the message next to it.
 */
function phantomForm(bounds) {
  const inputs = {};
  const errs = {};
  const labels = {};
  const fields = PHANTOM_FIELDS.map(([name, label, kind, def, c]) => {
    const input = kind === 'select'
      ? h('select', { name }, c.options.map((o) => h('option', { value: o, selected: o === def }, o)))
      : h('input', {
        name, type: 'number', value: String(def), min: c.min, max: limitAt(bounds, c.max), step: c.step, required: true,
      });
    inputs[name] = input;
    errs[name] = h('span.field-error', { dataset: { field: name } });
    labels[name] = h('label', { dataset: { field: name } }, label, input, errs[name]);
    return labels[name];
  });
  const formErr = h('div.form-error', { role: 'alert' });
  const sync = () => {
    const type = inputs.type.value;
    const algos = type === 'cone' ? ALGORITHMS_3D : ALGORITHMS_2D;
    const sel = inputs.algorithm;
    if (![...sel.options].some((o) => o.value === sel.value) || !algos.includes(sel.value)) {
      clear(sel).append(...algos.map((a) => h('option', { value: a }, a)));
    }
    for (const [name, , , , c] of PHANTOM_FIELDS) {
      const show = (!c.when || c.when.includes(type)) && (!c.algorithms || c.algorithms.includes(sel.value));
      labels[name].hidden = !show;
    }
  };
  inputs.type.addEventListener('change', sync);
  inputs.algorithm.addEventListener('change', sync);
  sync();
  const submit = h('button.primary', { type: 'submit' }, 'Simulate and reconstruct');
  const form = h('form#phantom-form', { novalidate: true }, h('div.form-grid', fields), h('div.row', submit), formErr);
  const place = (e) => {
    // Each field the problem points at gets its own detail; a pointer to no visible field, or a problem
    // without pointers, goes under the form.
    let placed = false;
    for (const f of e.errors || []) {
      const name = fieldOfPointer(f.pointer);
      if (name && !labels[name].hidden) {
        errs[name].append(errorBox({ title: e.title, detail: f.detail, code: e.code, pointer: f.pointer }));
        placed = true;
      }
    }
    if (!placed) formErr.append(errorBox(e));
  };
  form.addEventListener('submit', async (ev) => {
    ev.preventDefault();
    for (const e of Object.values(errs)) clear(e);
    clear(formErr);
    let bad = false;
    for (const [name, input] of Object.entries(inputs)) {
      if (!labels[name].hidden && input.validity && !input.validity.valid) {
        errs[name].textContent = input.validationMessage;
        bad = true;
      }
    }
    if (bad) return;
    const values = Object.fromEntries(Object.entries(inputs).map(([k, v]) => [k, v.value]));
    const { simulation, job } = phantomRequests(values);
    submit.disabled = true;
    try {
      const ds = await api('/v1/simulations', { method: 'POST', body: simulation });
      const j = await api('/v1/jobs', { method: 'POST', body: { input: ds.id, ...job } });
      location.hash = `#/job/${j.id}`;
    } catch (e) {
      place(e);
    } finally {
      submit.disabled = false;
    }
  });
  return form;
}

export async function showSend(main) {
  main.append(
    h('section.panel#send-dicom', h('h1', 'DICOM series'), dropZone(seriesActions)),
    h('section.panel#send-phantom', h('h2', 'Phantom: simulate and reconstruct'), phantomForm(await limits())),
  );
}

export async function showSeries(main, id, signal) {
  const s = await api(`/v1/series/${id}`, { signal });
  const facts = [
    ['Series', s.description || s.series_uid], ['Patient', s.patient_name || s.patient_id || '–'],
    ['Modality', s.modality || '–'], ['Instances', String(s.instances)], ['Shape', s.shape.join(' × ')],
    ['Spacing (mm)', s.frame.spacing_mm.map((x) => fmtNum(x, 4)).join(' × ')],
    ['HU range', `${fmtNum(s.hu_min, 0)} … ${fmtNum(s.hu_max, 0)}`], ['Tilt', `${fmtNum(s.tilt_deg, 2)}°`],
  ];
  const viewer = h('section.panel#slice-panel');
  main.append(h('section.panel#series-summary', h('h1', 'Series'),
    h('dl.facts', facts.map(([k, v]) => [h('dt', k), h('dd', v)])),
    (s.warnings || []).length ? h('ul.warnings', s.warnings.map((w) => h('li.warn', h('code', w.code), ' ', w.message))) : null,
    protocolForm(s.id)), viewer);
  const sv = new SliceViewer(viewer, { url: `/v1/series/${id}/volume.npy`, shape: s.shape, frame: s.frame, units: 'hu' });
  signal.addEventListener('abort', () => sv.destroy());
  await sv.start(signal);
}
