// .npy reading: the header of a float32 little-endian array, whole arrays and ranges of one.
// Volumes are [z][y][x] (slowest to fastest), as the API writes them.

/** Parse a .npy header from its first bytes: {shape, dtype, offset} or throws. */
export function parseHeader(buf) {
  const b = new Uint8Array(buf);
  if (b.length < 10 || b[0] !== 0x93 || String.fromCharCode(...b.slice(1, 6)) !== 'NUMPY') {
    throw new Error('not a .npy file');
  }
  const major = b[6];
  const dv = new DataView(buf instanceof ArrayBuffer ? buf : b.buffer);
  const len = major === 1 ? dv.getUint16(8, true) : dv.getUint32(8, true);
  const start = major === 1 ? 10 : 12;
  if (b.length < start + len) throw new Error('short .npy header');
  const text = new TextDecoder().decode(b.slice(start, start + len));
  const descr = /'descr':\s*'([^']+)'/.exec(text);
  const shape = /'shape':\s*\(([^)]*)\)/.exec(text);
  if (!descr || !shape) throw new Error('unreadable .npy header');
  if (/'fortran_order':\s*True/.test(text)) throw new Error('Fortran-ordered .npy is not supported');
  const dims = shape[1].split(',').map((s) => s.trim()).filter((s) => s).map(Number);
  return { dtype: descr[1], shape: dims, offset: start + len };
}

/**
 * Where the data of a float32 C-order `.npy` of `shape` start when the server wrote it: magic, version 1.0,
 * header length and the header dictionary, padded to a multiple of 64 bytes as numpy pads it. A guess to be
 * checked against the header read ({@link parseHeader}).
 */
export function expectedOffset(shape) {
  const dims = shape.length === 1 ? `(${shape[0]},)` : `(${shape.join(', ')})`;
  const dict = `{'descr': '<f4', 'fortran_order': False, 'shape': ${dims}, }`;
  const unpadded = 10 + dict.length + 1;
  return unpadded + ((64 - (unpadded % 64)) % 64);
}

/** The float32 values of a whole .npy body. */
export function decode(buf) {
  const h = parseHeader(buf);
  if (h.dtype !== '<f4') throw new Error(`unsupported dtype ${h.dtype}`);
  const n = h.shape.reduce((a, b) => a * b, 1);
  return { shape: h.shape, data: new Float32Array(buf.slice(h.offset, h.offset + 4 * n)) };
}
