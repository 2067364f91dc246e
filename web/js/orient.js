// Orientation labels (DESIGN §2): the patient direction each side of a screen image points to, as the server
// labels its own images (volume::direction_label): one letter per LPS component above 0.1, largest first,
// so an oblique image reads e.g. "LA" or "RP" as radiologists write it, and an axis-aligned one "L" or "A".

const LETTERS = [['R', 'L'], ['A', 'P'], ['I', 'S']];

/** Name of a patient direction (LPS vector): letters for every component above 0.1 in decreasing size. */
export function directionLabel(v) {
  return [0, 1, 2]
    .filter((c) => Math.abs(v[c]) > 0.1)
    .map((c) => [Math.abs(v[c]), LETTERS[c][v[c] > 0 ? 1 : 0]])
    .sort((a, b) => b[0] - a[0])
    .map(([, letter]) => letter)
    .join('');
}

const neg = (v) => v.map((x) => -x);

/**
 * The labels [top, bottom, left, right] of a plane of the slice viewer for a volume whose index axes i, j, k
 * point along direction[0], direction[1], direction[2] (LPS unit vectors). Axial shows i to the right and j
 * down; coronal i to the right and k up; sagittal j to the right and k up.
 */
export function planeSides(plane, direction) {
  const [di, dj, dk] = direction;
  const [right, down] = {
    axial: [di, dj],
    coronal: [di, neg(dk)],
    sagittal: [dj, neg(dk)],
  }[plane];
  return [directionLabel(neg(down)), directionLabel(down), directionLabel(neg(right)), directionLabel(right)];
}
