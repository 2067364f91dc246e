// The choices of the phantom forms. The enums and minimums follow openapi.yaml, the maximums come from
// `GET /v1/limits`; the server checks everything again at submission (and the memory budget) and its problem
// is shown next to the field its JSON Pointer names. (Volume protocols are the server's: `GET /v1/protocols`,
// see api.js.)

export const PHANTOM_TABLES = ['modified_shepp_logan', 'shepp_logan', 'yu_ye_wang'];
export const FILTERS = ['ram-lak', 'shepp-logan', 'cosine', 'hamming', 'hann'];
export const ALGORITHMS_2D = ['fbp', 'art', 'sart', 'os_sart', 'sirt', 'cgls', 'mlem', 'tv'];
export const ALGORITHMS_3D = ['fdk', 'sirt', 'cgls', 'sart'];

/**
 * Fields of the phantom form: [name, label, kind, default, constraints]. `when` limits a field to some
 * geometry types. `max` names the bound of `GET /v1/limits` that the server checks the field against
 * (a path into that answer); counts start at 1 and lengths above 0, as the server's validators say.
 */
export const PHANTOM_FIELDS = [
  ['table', 'Phantom', 'select', 'modified_shepp_logan', { options: PHANTOM_TABLES }],
  ['scale_mm', 'Phantom radius (mm)', 'number', 100, { min: 0.001, step: 'any' }],
  ['type', 'Geometry', 'select', 'parallel', { options: ['parallel', 'fan', 'cone'] }],
  ['views', 'Views', 'number', 180, { min: 1, step: 1, max: 'geometry.max_views' }],
  ['det_count', 'Detector elements (columns)', 'number', 256, { min: 1, step: 1, max: 'geometry.max_detector_elements' }],
  ['det_spacing_mm', 'Detector spacing (mm)', 'number', 1, { min: 0.001, step: 'any' }],
  ['dso_mm', 'Source–centre (mm)', 'number', 500, { min: 0.001, step: 'any', when: ['fan', 'cone'] }],
  ['dsd_mm', 'Source–detector (mm)', 'number', 900, { min: 0.001, step: 'any', when: ['fan', 'cone'] }],
  ['nv', 'Detector rows', 'number', 128, { min: 1, step: 1, when: ['cone'], max: 'geometry.max_detector_elements' }],
  ['noise', 'Incident photons (0: exact)', 'number', 0, { min: 0, step: 'any', max: 'simulation.max_incident_photons' }],
  ['algorithm', 'Algorithm', 'select', 'fbp', { options: ALGORITHMS_2D }],
  ['filter', 'Filter', 'select', 'ram-lak', { options: FILTERS, algorithms: ['fbp', 'fdk'] }],
  ['iterations', 'Iterations', 'number', 20, {
    min: 1, step: 1, max: 'algorithm.max_iterations', algorithms: ['art', 'sart', 'os_sart', 'sirt', 'cgls', 'mlem', 'tv'],
  }],
  ['size', 'Grid size (pixels per side)', 'number', 256, { min: 1, step: 1, max: 'grid.max_side' }],
  ['pixel_mm', 'Pixel size (mm)', 'number', 1, { min: 0.001, step: 'any' }],
];

/** The bound at `path` (`geometry.max_views`) of the `GET /v1/limits` answer, or undefined. */
export function limitAt(limits, path) {
  return path ? path.split('.').reduce((o, k) => (o == null ? undefined : o[k]), limits) : undefined;
}

/**
 * Where the fields of the two request bodies the form sends live: JSON Pointers of the simulation and the
 * job, each to its form field. A problem's pointer goes to the field of its longest listed prefix.
 */
export const POINTER_FIELDS = {
  '/phantom': 'table', '/phantom/table': 'table', '/phantom/scale_mm': 'scale_mm',
  '/geometry/type': 'type', '/geometry/angles': 'views',
  '/geometry/det_count': 'det_count', '/geometry/detector/count': 'det_count', '/geometry/detector/nu': 'det_count',
  '/geometry/det_spacing_mm': 'det_spacing_mm', '/geometry/detector/spacing_mm': 'det_spacing_mm',
  '/geometry/detector/du_mm': 'det_spacing_mm', '/geometry/detector/dv_mm': 'det_spacing_mm',
  '/geometry/dso_mm': 'dso_mm', '/geometry/dsd_mm': 'dsd_mm', '/geometry/detector/nv': 'nv',
  '/noise': 'noise', '/algorithm': 'algorithm', '/algorithm/filter': 'filter', '/algorithm/iterations': 'iterations',
  '/grid': 'size', '/grid/dx_mm': 'pixel_mm', '/grid/dy_mm': 'pixel_mm', '/grid/spacing_mm': 'pixel_mm',
};

/** The form field of a pointer into the simulation or job body, or null (the form as a whole). */
export function fieldOfPointer(pointer) {
  const parts = String(pointer || '').split('/');
  for (let n = parts.length; n > 1; n -= 1) {
    const field = POINTER_FIELDS[parts.slice(0, n).join('/')];
    if (field) return field;
  }
  return null;
}

/** The simulation and job bodies of the phantom form's values. */
export function phantomRequests(v) {
  const n = (k) => Number(v[k]);
  let geometry;
  if (v.type === 'parallel') {
    geometry = { type: 'parallel', angles: { count: n('views') }, det_count: n('det_count'), det_spacing_mm: n('det_spacing_mm') };
  } else if (v.type === 'fan') {
    geometry = {
      type: 'fan', angles: { count: n('views') }, dso_mm: n('dso_mm'), dsd_mm: n('dsd_mm'),
      detector: { shape: 'flat', count: n('det_count'), spacing_mm: n('det_spacing_mm') },
    };
  } else {
    geometry = {
      type: 'cone', angles: { count: n('views') }, dso_mm: n('dso_mm'), dsd_mm: n('dsd_mm'),
      detector: { nu: n('det_count'), nv: n('nv'), du_mm: n('det_spacing_mm'), dv_mm: n('det_spacing_mm') },
    };
  }
  const simulation = { phantom: { table: v.table, scale_mm: n('scale_mm') }, geometry };
  if (n('noise') > 0) simulation.noise = { incident_photons: n('noise'), seed: 1 };
  const algorithm = { name: v.algorithm };
  if (['fbp', 'fdk'].includes(v.algorithm)) algorithm.filter = v.filter;
  else algorithm.iterations = n('iterations');
  const size = n('size');
  const px = n('pixel_mm');
  const grid = v.type === 'cone'
    ? { nx: size, ny: size, nz: size, spacing_mm: [px, px, px] }
    : { nx: size, ny: size, dx_mm: px, dy_mm: px };
  return { simulation, job: { algorithm, grid, outputs: ['volume', 'metrics'] } };
}
