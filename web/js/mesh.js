// The STL mesh in WebGL (three.js, vendored): rotate, zoom and pan with the mouse or keys, a clipping plane
// along a patient axis for cut-away views, and the triangle count read from the file beside the API's
// figures. Binary STL in mm, LPS; the camera starts anterior (looking along +y, superior up).

import * as THREE from '../vendor/three/three.module.js';
import { OrbitControls } from '../vendor/three/OrbitControls.js';
import { bytes } from './api.js';
import { h } from './dom.js';
import { directionLabel } from './orient.js';

/** The patient direction (LPS: +x left, +y posterior, +z superior) of a world vector, combined when oblique. */
function side(v) {
  return directionLabel([v.x, v.y, v.z]);
}

/** Positions and normals of a binary STL: {positions, normals, triangles}. */
export function parseStl(buf) {
  const dv = new DataView(buf);
  if (buf.byteLength < 84) throw new Error('STL too short');
  const n = dv.getUint32(80, true);
  if (84 + n * 50 > buf.byteLength) throw new Error('STL shorter than its triangle count');
  const positions = new Float32Array(n * 9);
  const normals = new Float32Array(n * 9);
  for (let t = 0; t < n; t += 1) {
    const o = 84 + t * 50;
    const nx = dv.getFloat32(o, true);
    const ny = dv.getFloat32(o + 4, true);
    const nz = dv.getFloat32(o + 8, true);
    for (let v = 0; v < 3; v += 1) {
      for (let c = 0; c < 3; c += 1) positions[t * 9 + v * 3 + c] = dv.getFloat32(o + 12 + v * 12 + c * 4, true);
      normals[t * 9 + v * 3] = nx;
      normals[t * 9 + v * 3 + 1] = ny;
      normals[t * 9 + v * 3 + 2] = nz;
    }
  }
  return { positions, normals, triangles: n };
}

export class MeshView {
  constructor(root, url) {
    this.root = root;
    this.url = url;
    this.frames = 0;
    this.labels = Object.fromEntries(['top', 'bottom', 'left', 'right']
      .map((k) => [k, h(`span.orient.orient-${k}`, { dataset: { side: k } })]));
    this.canvasHolder = h('div.mesh-stage#mesh-stage', Object.values(this.labels));
    this.count = h('span#mesh-triangles', '…');
    this.axis = h('select#clip-axis', { 'aria-label': 'clipping plane' },
      [['', 'no clipping'], ['x', 'sagittal (R–L)'], ['y', 'coronal (A–P)'], ['z', 'axial (S–I)']]
        .map(([v, t]) => h('option', { value: v }, t)));
    this.pos = h('input#clip-position', { type: 'range', min: '0', max: '1000', value: '500', 'aria-label': 'clip position' });
    this.flip = h('button#clip-flip', { type: 'button' }, 'Flip side');
    this.reset = h('button#mesh-reset', { type: 'button' }, 'Reset view');
    root.append(h('div.row', h('span', 'Triangles in file: ', this.count), this.axis, this.pos, this.flip, this.reset),
      this.canvasHolder,
      h('p.muted.hint', 'drag: rotate · right-drag or shift-drag: pan · wheel: zoom · arrows: rotate (canvas focused)'));
  }

  async load(signal) {
    const buf = await bytes(this.url, null, signal);
    const stl = parseStl(buf);
    this.count.textContent = String(stl.triangles);
    this.count.dataset.count = String(stl.triangles);
    const renderer = new THREE.WebGLRenderer({ antialias: true, preserveDrawingBuffer: true });
    this.renderer = renderer;
    renderer.setPixelRatio(Math.min(window.devicePixelRatio || 1, 2));
    renderer.localClippingEnabled = true;
    renderer.setClearColor(0x000000, 1);
    const canvas = renderer.domElement;
    canvas.tabIndex = 0;
    canvas.setAttribute('aria-label', 'mesh view');
    canvas.id = 'mesh-canvas';
    this.canvasHolder.append(canvas);

    const geom = new THREE.BufferGeometry();
    geom.setAttribute('position', new THREE.BufferAttribute(stl.positions, 3));
    geom.setAttribute('normal', new THREE.BufferAttribute(stl.normals, 3));
    geom.computeBoundingBox();
    geom.computeBoundingSphere();
    const box = geom.boundingBox;
    const centre = box.getCenter(new THREE.Vector3());
    const radius = geom.boundingSphere.radius || 1;
    this.box = box;
    this.plane = new THREE.Plane(new THREE.Vector3(1, 0, 0), 0);
    const material = new THREE.MeshStandardMaterial({
      color: 0xe8dcc4, roughness: 0.6, metalness: 0.0, side: THREE.DoubleSide, clippingPlanes: [],
    });
    this.material = material;
    const scene = new THREE.Scene();
    scene.add(new THREE.Mesh(geom, material));
    scene.add(new THREE.HemisphereLight(0xffffff, 0x404040, 1.6));
    const light = new THREE.DirectionalLight(0xffffff, 1.8);
    scene.add(light);
    const camera = new THREE.PerspectiveCamera(35, 1, radius / 100, radius * 20);
    this.home = () => {
      // Anterior view: the camera on −y (anterior in LPS) looking along +y, superior (+z) up.
      camera.position.set(centre.x, centre.y - radius * 3.2, centre.z);
      camera.up.set(0, 0, 1);
      camera.lookAt(centre);
      this.controls.target.copy(centre);
      this.controls.update();
    };
    this.controls = new OrbitControls(camera, canvas);
    this.controls.listenToKeyEvents(canvas);
    this.controls.keyRotateSpeed = 1.0;
    // Drawn on demand (a camera move, a clip change, a resize), at most once per animation frame: an idle
    // view costs nothing, which matters with software GL and meshes of 10⁵ triangles and more.
    const draw = () => {
      this.raf = 0;
      light.position.copy(camera.position);
      renderer.render(scene, camera);
      this.orient();
      this.frames += 1;
      canvas.dataset.frames = String(this.frames);
    };
    const redraw = () => {
      if (!this.raf) this.raf = requestAnimationFrame(draw);
    };
    this.controls.addEventListener('change', redraw);
    this.home();
    this.scene = scene;
    this.camera = camera;
    this.light = light;
    const resize = () => {
      const w = this.canvasHolder.clientWidth || 640;
      const hgt = this.canvasHolder.clientHeight || 480;
      renderer.setSize(w, hgt, false);
      camera.aspect = w / hgt;
      camera.updateProjectionMatrix();
      redraw();
    };
    this.onResize = resize;
    window.addEventListener('resize', resize);
    resize();
    const clip = () => {
      const a = this.axis.value;
      redraw();
      if (!a) {
        material.clippingPlanes = [];
        return;
      }
      const t = Number(this.pos.value) / 1000;
      const lo = box.min[a];
      const hi = box.max[a];
      const n = new THREE.Vector3(a === 'x' ? 1 : 0, a === 'y' ? 1 : 0, a === 'z' ? 1 : 0);
      if (this.flipped) n.negate();
      this.plane.normal.copy(n);
      this.plane.constant = -n.dot(new THREE.Vector3().setComponent('xyz'.indexOf(a), lo + t * (hi - lo)));
      material.clippingPlanes = [this.plane];
    };
    this.axis.addEventListener('change', clip);
    this.pos.addEventListener('input', clip);
    this.flip.addEventListener('click', () => {
      this.flipped = !this.flipped;
      clip();
    });
    this.reset.addEventListener('click', () => {
      this.home();
      redraw();
    });
    redraw();
    this.root.dataset.meshLoaded = 'true';
  }

  /** Screen sides in patient directions, from the camera's right and up axes. */
  orient() {
    const right = new THREE.Vector3().setFromMatrixColumn(this.camera.matrixWorld, 0);
    const up = new THREE.Vector3().setFromMatrixColumn(this.camera.matrixWorld, 1);
    const sides = { right: side(right), left: side(right.clone().negate()), top: side(up), bottom: side(up.clone().negate()) };
    for (const [k, el] of Object.entries(this.labels)) el.textContent = sides[k];
  }

  destroy() {
    if (this.raf) cancelAnimationFrame(this.raf);
    if (this.onResize) window.removeEventListener('resize', this.onResize);
    if (this.controls) this.controls.dispose();
    if (this.renderer) this.renderer.dispose();
  }
}
