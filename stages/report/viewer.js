// The report's 3D viewer: each key frame's lumen as tubes coloured by diameter, on three.js (WebGL).
// three.js is embedded as text in the page (#three-src) and imported from a blob: URL, so the report needs
// no network and no file beside it. World coordinates are DICOM LPS in mm; +z (head) is up on the screen.
const model = JSON.parse(document.getElementById('model').textContent);
const canvas = document.getElementById('view3d');
const labelsDiv = document.getElementById('labels');
const slider = document.getElementById('frame');
const errorBox = document.getElementById('viewer-error');

function fail(message) {
  errorBox.hidden = false;
  errorBox.textContent = message;
  canvas.dataset.state = 'failed';
}

let THREE = null;
try {
  const source = document.getElementById('three-src').textContent;
  const url = URL.createObjectURL(new Blob([source], {type: 'text/javascript'}));
  THREE = await import(url);
  URL.revokeObjectURL(url);
} catch (err) {
  fail('The 3D view could not start its embedded three.js (' + err + ').');
}

// diameter colour map (perceptually ordered, dark blue -> yellow): stops of t in [0, 1]
const STOPS = [[0.0, [0.27, 0.00, 0.33]], [0.25, [0.23, 0.32, 0.55]], [0.5, [0.13, 0.57, 0.55]],
               [0.75, [0.37, 0.79, 0.38]], [1.0, [0.99, 0.91, 0.14]]];
function colourOf(diameter) {
  const [lo, hi] = model.diameter_mm;
  const t = Math.min(Math.max((diameter - lo) / Math.max(hi - lo, 1e-6), 0), 1);
  for (let i = 1; i < STOPS.length; i++) {
    if (t <= STOPS[i][0]) {
      const [t0, c0] = STOPS[i - 1], [t1, c1] = STOPS[i], u = (t - t0) / (t1 - t0);
      return c0.map((c, k) => c + u * (c1[k] - c));
    }
  }
  return STOPS[STOPS.length - 1][1];
}

function colourBar() {
  const gradient = STOPS.map(([t, c]) => `rgb(${c.map(v => Math.round(255 * v)).join(',')}) ${100 * t}%`).join(', ');
  document.getElementById('cbar').style.background = `linear-gradient(to right, ${gradient})`;
  document.getElementById('cbar-min').textContent = model.diameter_mm[0].toFixed(1);
  document.getElementById('cbar-max').textContent = model.diameter_mm[1].toFixed(1);
}

const SIDES = 12;

// One branch (node path) as a tube: rings around the centreline, each ring's frame carried along the path
// (parallel transport) so the tube does not twist; vertices coloured by the node's diameter.
function addTube(path, nodes, radius, out) {
  const n = path.length;
  if (n < 2) { return; }
  const P = path.map(i => new THREE.Vector3(...nodes[i]));
  const tangents = P.map((p, k) => {
    const a = P[Math.max(k - 1, 0)], b = P[Math.min(k + 1, n - 1)];
    const t = new THREE.Vector3().subVectors(b, a);
    return t.lengthSq() > 0 ? t.normalize() : new THREE.Vector3(0, 0, 1);
  });
  let normal = new THREE.Vector3(0, 0, 1);
  if (Math.abs(normal.dot(tangents[0])) > 0.9) { normal.set(1, 0, 0); }
  normal.sub(tangents[0].clone().multiplyScalar(normal.dot(tangents[0]))).normalize();
  const base = out.positions.length / 3;
  for (let k = 0; k < n; k++) {
    if (k > 0) {  // carry the normal from the previous ring
      normal.sub(tangents[k].clone().multiplyScalar(normal.dot(tangents[k])));
      if (normal.lengthSq() < 1e-12) { normal = new THREE.Vector3(1, 0, 0); }
      normal.normalize();
    }
    const binormal = new THREE.Vector3().crossVectors(tangents[k], normal);
    const r = radius[path[k]], c = colourOf(2 * r);
    for (let j = 0; j < SIDES; j++) {
      const a = 2 * Math.PI * j / SIDES, ca = Math.cos(a), sa = Math.sin(a);
      const dir = normal.clone().multiplyScalar(ca).add(binormal.clone().multiplyScalar(sa));
      out.positions.push(P[k].x + r * dir.x, P[k].y + r * dir.y, P[k].z + r * dir.z);
      out.normals.push(dir.x, dir.y, dir.z);
      out.colours.push(...c);
    }
  }
  for (let k = 0; k < n - 1; k++) {
    for (let j = 0; j < SIDES; j++) {
      const a = base + k * SIDES + j, b = base + k * SIDES + (j + 1) % SIDES;
      const c = a + SIDES, d = b + SIDES;
      out.indices.push(a, c, b, b, c, d);
    }
  }
}

function meshOf(buffers, material) {
  const g = new THREE.BufferGeometry();
  g.setAttribute('position', new THREE.Float32BufferAttribute(buffers.positions, 3));
  g.setAttribute('normal', new THREE.Float32BufferAttribute(buffers.normals, 3));
  g.setAttribute('color', new THREE.Float32BufferAttribute(buffers.colours, 3));
  g.setIndex(buffers.indices);
  return new THREE.Mesh(g, material);
}

function frameGroup(f, materials, sphere) {
  const group = new THREE.Group();
  const oneView = new Set(f.one_view);
  const both = {positions: [], normals: [], colours: [], indices: []};
  const single = {positions: [], normals: [], colours: [], indices: []};
  const degree = new Map();
  f.segments.forEach((seg, i) => {
    addTube(seg, f.nodes, f.radius, oneView.has(i) ? single : both);
    for (const end of [seg[0], seg[seg.length - 1]]) { degree.set(end, (degree.get(end) || 0) + 1); }
  });
  if (both.indices.length) { group.add(meshOf(both, materials.both)); }
  if (single.indices.length) { group.add(meshOf(single, materials.single)); }
  // round caps at junctions and ends, so branches meet without gaps
  for (const node of degree.keys()) {
    const r = f.radius[node];
    const m = new THREE.Mesh(sphere, new THREE.MeshPhongMaterial({color: new THREE.Color(...colourOf(2 * r)), shininess: 40}));
    m.position.set(...f.nodes[node]);
    m.scale.setScalar(r);
    group.add(m);
  }
  // lesions: a red ring at the lesion's point, facing the camera (grey: a narrowing the views do not confirm)
  for (const les of model.lesions) {
    if (les.node >= f.nodes.length) { continue; }
    const ring = new THREE.Mesh(new THREE.TorusGeometry(Math.max(2.5, 1.6 * les.reference / 2 + 1), 0.35, 8, 32),
                                les.unconfirmed ? materials.unconfirmed : materials.lesion);
    ring.position.set(...f.nodes[les.node]);
    ring.userData.faceCamera = true;
    group.add(ring);
  }
  // each run's C-arm: the source, the central ray, the beam's edges cut at the tree's depth
  for (const [name, cam] of Object.entries(f.cameras)) {
    const src = new THREE.Vector3(...cam.source);
    const material = materials.carm[name] || materials.carm.a;
    group.add(new THREE.LineSegments(new THREE.BufferGeometry().setFromPoints([src, new THREE.Vector3(...cam.ray_end)]),
                                     material.ray));
    const beam = [], corners = cam.corners.map(c => new THREE.Vector3(...c));
    for (let k = 0; k < 4; k++) { beam.push(src, corners[k], corners[k], corners[(k + 1) % 4]); }
    group.add(new THREE.LineSegments(new THREE.BufferGeometry().setFromPoints(beam), material.beam));
    const s = new THREE.Mesh(sphere, materials.source);
    s.position.copy(src);
    s.scale.setScalar(12);
    group.add(s);
  }
  group.visible = false;
  return group;
}

// --- camera control: orbit around a target, +z up; pan moves the target; zoom changes the distance
const view = {theta: -Math.PI / 2, phi: Math.PI / 2, distance: 1, target: null};
let camera = null, renderer = null, scene = null;

function place() {
  const s = Math.sin(view.phi);
  camera.position.set(view.target.x + view.distance * s * Math.cos(view.theta),
                      view.target.y + view.distance * s * Math.sin(view.theta),
                      view.target.z + view.distance * Math.cos(view.phi));
  camera.up.set(0, 0, 1);
  camera.lookAt(view.target);
  camera.near = Math.max(view.distance / 1000, 0.1);
  camera.far = view.distance * 20 + 5000;
  camera.updateProjectionMatrix();
}

function reset(withCarm) {
  view.theta = -Math.PI / 2;  // from the patient's front (antero-posterior): patient's left on screen right
  view.phi = Math.PI / 2;
  view.target = new THREE.Vector3(...model.centre);
  let radius = 0.75 * model.extent;
  if (withCarm) {
    for (const f of model.frames) {
      for (const cam of Object.values(f.cameras)) {
        radius = Math.max(radius, view.target.distanceTo(new THREE.Vector3(...cam.source)));
      }
    }
  }
  view.distance = radius / Math.tan(THREE.MathUtils.degToRad(camera.fov / 2)) * 1.1;
  place();
}

let current = 0, labelEls = [], needsRender = true;
const groups = [];

function projectToScreen(p) {
  const v = p.clone().project(camera);
  return {x: (v.x + 1) / 2 * canvas.clientWidth, y: (1 - v.y) / 2 * canvas.clientHeight, visible: v.z < 1 && v.z > -1};
}

function buildLabels() {
  labelsDiv.textContent = '';
  labelEls = [];
  for (const v of model.vessels) {
    const el = document.createElement('div');
    el.className = 'vessel';
    el.textContent = v.name;
    labelsDiv.appendChild(el);
    labelEls.push({el, node: v.node});
  }
  for (const les of model.lesions) {
    const el = document.createElement('button');
    el.type = 'button';
    el.className = les.unconfirmed ? 'lesion unconfirmed' : 'lesion';
    el.dataset.lesion = les.id;
    el.textContent = `${les.vessel} ${les.ds.toFixed(0)} % · ${les.length.toFixed(1)} mm` +
      (les.unconfirmed ? ' · unconfirmed' : '');
    el.title = 'show the diameter profile';
    el.addEventListener('click', () => showLesion(les));
    labelsDiv.appendChild(el);
    labelEls.push({el, node: les.node});
  }
  for (const name of Object.keys(model.frames[0] ? model.frames[0].cameras : {})) {
    const el = document.createElement('div');
    el.className = 'carm';
    el.textContent = name.toUpperCase() + (model.frames[0].cameras[name].angles ? ' ' + model.frames[0].cameras[name].angles : '');
    labelsDiv.appendChild(el);
    labelEls.push({el, camera: name});
  }
}

function placeLabels() {
  const f = model.frames[current];
  if (!f) { return; }  // a reconstruction without key frames: nothing to label
  for (const item of labelEls) {
    let p;
    if (item.camera) {
      const cam = f.cameras[item.camera];
      if (!cam) { item.el.hidden = true; continue; }
      p = new THREE.Vector3(...cam.source);
    } else {
      if (item.node >= f.nodes.length) { item.el.hidden = true; continue; }
      p = new THREE.Vector3(...f.nodes[item.node]);
    }
    const s = projectToScreen(p);
    const inside = s.visible && s.x >= 0 && s.y >= 0 && s.x <= canvas.clientWidth && s.y <= canvas.clientHeight;
    item.el.hidden = !inside || !document.getElementById('show-labels').checked;
    item.el.style.left = s.x + 'px';
    item.el.style.top = s.y + 'px';
  }
}

function showLesion(les) {
  document.getElementById('lesion-text').textContent =
    `${les.vessel}${les.segment ? ' (' + les.segment + ')' : ''}: ${les.ds.toFixed(0)} % diameter stenosis, ` +
    `MLD ${les.mld.toFixed(2)} mm, reference ${les.reference.toFixed(2)} mm, length ${les.length.toFixed(1)} mm, ` +
    `${les.position.toFixed(1)} mm from the vessel's origin (QCA key frame ${model.qca_frame}).` +
    (les.unconfirmed ? ` Not reported as a lesion: ${les.unconfirmed}.` : '');
  document.getElementById('lesion-profile').innerHTML = les.svg;
  const panel = document.getElementById('lesion-panel');
  panel.hidden = false;
  panel.dataset.lesion = les.id;
}

function showFrame(k) {
  if (!model.frames.length) { return; }
  current = (k + model.frames.length) % model.frames.length;
  groups.forEach((g, i) => { g.visible = i === current; });
  const f = model.frames[current];
  slider.value = String(current);
  document.getElementById('frame_label').textContent = f.key;
  const phases = Object.entries(f.phase).map(([run, p]) => `${run.toUpperCase()} ${Number(p).toFixed(2)}`).join(', ');
  document.getElementById('phase_label').textContent = phases ? `— cardiac phase ${phases} (0 = R wave)` : '';
  const img = document.getElementById('overlay');
  if (f.overlay) { img.src = f.overlay; img.hidden = false; } else { img.hidden = true; }
  document.getElementById('overlay-caption').textContent = `key frame ${f.key}: the model reprojected on both runs`;
  canvas.dataset.frame = f.key;
  needsRender = true;
}

function renderNow() {
  scene.traverse(o => { if (o.userData.faceCamera) { o.quaternion.copy(camera.quaternion); } });
  renderer.render(scene, camera);
  placeLabels();
  canvas.dataset.rendered = String(Number(canvas.dataset.rendered || 0) + 1);
}

function loop() {
  if (needsRender) { needsRender = false; renderNow(); }
  requestAnimationFrame(loop);
}

function controls() {
  let drag = null;
  canvas.addEventListener('contextmenu', e => e.preventDefault());
  canvas.addEventListener('pointerdown', e => {
    drag = {x: e.clientX, y: e.clientY, pan: e.button === 2 || e.shiftKey,
            theta: view.theta, phi: view.phi, target: view.target.clone()};
    canvas.setPointerCapture(e.pointerId);
  });
  canvas.addEventListener('pointerup', e => { drag = null; canvas.releasePointerCapture(e.pointerId); });
  canvas.addEventListener('pointermove', e => {
    if (!drag) { return; }
    const dx = e.clientX - drag.x, dy = e.clientY - drag.y;
    if (drag.pan) {  // move the target in the screen plane, at the target's depth
      const scale = 2 * view.distance * Math.tan(THREE.MathUtils.degToRad(camera.fov / 2)) / canvas.clientHeight;
      const right = new THREE.Vector3().setFromMatrixColumn(camera.matrixWorld, 0);
      const up = new THREE.Vector3().setFromMatrixColumn(camera.matrixWorld, 1);
      view.target.copy(drag.target).addScaledVector(right, -dx * scale).addScaledVector(up, dy * scale);
    } else {
      view.theta = drag.theta - dx * 0.01;
      view.phi = Math.min(Math.max(drag.phi - dy * 0.01, 0.01), Math.PI - 0.01);
    }
    place();
    needsRender = true;
  });
  canvas.addEventListener('wheel', e => {
    e.preventDefault();
    view.distance *= Math.exp(e.deltaY * 0.001);
    place();
    needsRender = true;
  }, {passive: false});
  canvas.addEventListener('dblclick', () => { reset(false); needsRender = true; });
  document.getElementById('reset').addEventListener('click', () => { reset(false); needsRender = true; });
  document.getElementById('fit-carm').addEventListener('click', () => { reset(true); needsRender = true; });
  document.getElementById('show-labels').addEventListener('change', () => { needsRender = true; });
  document.getElementById('lesion-close').addEventListener('click', () => {
    document.getElementById('lesion-panel').hidden = true;
  });
  slider.max = String(Math.max(model.frames.length - 1, 0));
  slider.addEventListener('input', () => showFrame(Number(slider.value)));
  let timer = null;
  const play = document.getElementById('play');
  play.addEventListener('click', () => {
    if (timer) { clearInterval(timer); timer = null; play.textContent = '▶ play'; return; }
    timer = setInterval(() => showFrame(current + 1), 400);
    play.textContent = '❚❚ pause';
  });
}

function start() {
  try {
    renderer = new THREE.WebGLRenderer({canvas, antialias: true});
  } catch (err) {
    fail('This browser could not open a WebGL context for the 3D view (' + err.message + ').');
    return;
  }
  renderer.setPixelRatio(window.devicePixelRatio || 1);
  renderer.setSize(canvas.clientWidth || canvas.width, canvas.clientHeight || canvas.height, false);
  renderer.setClearColor(0x111111);
  scene = new THREE.Scene();
  camera = new THREE.PerspectiveCamera(30, canvas.width / canvas.height, 0.1, 10000);
  scene.add(camera);
  scene.add(new THREE.HemisphereLight(0xffffff, 0x303040, 1.2));
  const light = new THREE.DirectionalLight(0xffffff, 1.6);
  light.position.set(0.3, 0.5, 1);
  camera.add(light);  // a head light: the side facing the user is lit whatever the orientation
  const materials = {
    both: new THREE.MeshPhongMaterial({vertexColors: true, shininess: 40}),
    single: new THREE.MeshPhongMaterial({vertexColors: true, transparent: true, opacity: 0.3, depthWrite: false}),
    lesion: new THREE.MeshBasicMaterial({color: 0xe53935}),
    unconfirmed: new THREE.MeshBasicMaterial({color: 0x9e9e9e}),
    source: new THREE.MeshBasicMaterial({color: 0xffd54f}),
    carm: Object.fromEntries([['a', 0xffb74d], ['b', 0x4fc3f7]].map(([name, color]) => [name, {
      ray: new THREE.LineBasicMaterial({color}),
      beam: new THREE.LineBasicMaterial({color, transparent: true, opacity: 0.25}),
    }])),
  };
  const sphere = new THREE.SphereGeometry(1, 16, 12);
  for (const f of model.frames) {
    const g = frameGroup(f, materials, sphere);
    scene.add(g);
    groups.push(g);
  }
  colourBar();
  reset(false);
  buildLabels();
  controls();
  showFrame(0);
  renderNow();
  canvas.dataset.state = 'ready';
  requestAnimationFrame(loop);
}

if (THREE) { start(); }
