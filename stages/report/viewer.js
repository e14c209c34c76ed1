// The report's 3D view: a canvas drawing of each key frame's centreline graph, drag to rotate.
const model = JSON.parse(document.getElementById('model').textContent);
const canvas = document.getElementById('view3d');
const ctx = canvas.getContext('2d');
let yaw = 0.6, pitch = -0.3, frame = 0, drag = null;

function colour(t) { const h = 240 - 240 * t; return `hsl(${h},90%,50%)`; }

function draw() {
  const f = model.frames[frame];
  ctx.fillStyle = '#111';
  ctx.fillRect(0, 0, canvas.width, canvas.height);
  if (!f || f.nodes.length === 0) { return; }
  const c = model.centre, s = canvas.width / (1.2 * model.extent);
  const cy = Math.cos(yaw), sy = Math.sin(yaw), cp = Math.cos(pitch), sp = Math.sin(pitch);
  const P = f.nodes.map(p => {
    const x = p[0] - c[0], y = p[1] - c[1], z = p[2] - c[2];
    const x1 = cy * x + sy * y, y1 = -sy * x + cy * y;
    const y2 = cp * y1 - sp * z, z2 = sp * y1 + cp * z;
    return [canvas.width / 2 + s * x1, canvas.height / 2 - s * z2, y2];
  });
  // far edges first, so near ones are drawn over them
  const order = f.edges.map((e, i) => i).sort((i, j) => (P[f.edges[j][0]][2] - P[f.edges[i][0]][2]));
  for (const i of order) {
    const [a, b] = f.edges[i];
    ctx.strokeStyle = colour(0.5 * (f.pos[a] + f.pos[b]));
    ctx.lineWidth = Math.max(1, s * (f.radius[a] + f.radius[b]));
    ctx.lineCap = 'round';
    ctx.beginPath(); ctx.moveTo(P[a][0], P[a][1]); ctx.lineTo(P[b][0], P[b][1]); ctx.stroke();
  }
}

canvas.onmousedown = e => drag = [e.clientX, e.clientY, yaw, pitch];
window.onmouseup = () => drag = null;
window.onmousemove = e => {
  if (drag) { yaw = drag[2] + (e.clientX - drag[0]) / 150; pitch = drag[3] + (e.clientY - drag[1]) / 150; draw(); }
};
const slider = document.getElementById('frame');
slider.max = model.frames.length - 1;
slider.oninput = () => {
  frame = +slider.value;
  document.getElementById('frame_label').textContent = model.frames[frame].key;
  draw();
};
document.getElementById('frame_label').textContent = model.frames.length ? model.frames[0].key : '';
draw();
