// mi-amr view: the orbit camera's arithmetic, as mi_amr/view/camera.py does
// it (the server applies the same clamps to what the page sends), and the
// orientation axes drawn from it.

const cross = (p, q) => [p[1] * q[2] - p[2] * q[1], p[2] * q[0] - p[0] * q[2], p[0] * q[1] - p[1] * q[0]];
const norm = (p) => { const l = Math.hypot(...p); return p.map((x) => x / l); };
const dot = (p, q) => p[0] * q[0] + p[1] * q[1] + p[2] * q[2];
const DEG = Math.PI / 180;

// The orbit's frame: e1, e2 span the plane normal to up (camera.py _frame).
function frame(up) {
  const u = norm(up), h = Math.abs(u[0]) < 0.9 ? [1, 0, 0] : [0, 1, 0];
  const e1 = norm(cross(h, u));
  return { e1, e2: cross(u, e1), u };
}

// Camera right, up and toward-the-eye unit vectors, as the picture shows them.
export function basis(camera) {
  const { e1, e2, u } = frame(camera.up);
  const a = camera.azimuth * DEG, e = camera.elevation * DEG;
  const back = [0, 1, 2].map((i) => Math.cos(e) * (Math.cos(a) * e1[i] + Math.sin(a) * e2[i]) + Math.sin(e) * u[i]);
  const right = norm(cross(u, back));
  return { right, up: cross(back, right), back };
}

// The least elevation an orbit or zoom may take (OrbitCamera.lowest_elevation):
// the eye `margin` of the distance above the floor, unless the target is below it.
export function lowestElevation(camera, maxElevation, margin) {
  if (camera.floor === null || camera.floor === undefined) return -maxElevation;
  const height = dot(camera.target, norm(camera.up));
  if (height < camera.floor) return -maxElevation;
  const s = Math.max(-1, Math.min(1, (camera.floor - height) / camera.distance + margin));
  return Math.max(-maxElevation, Math.min(maxElevation, Math.asin(s) / DEG));
}

// The elevation `el` within the poles and above the floor.
export function clampElevation(camera, el, maxElevation, margin) {
  return Math.min(maxElevation, Math.max(lowestElevation(camera, maxElevation, margin), el));
}

// x (red), y (green), z (blue) world axes as the camera sees them, in a small canvas.
export function drawAxes(canvas, camera) {
  const c = canvas.getContext("2d"), w = canvas.width, h = canvas.height, r = 0.36 * Math.min(w, h);
  const { right, up, back } = basis(camera);
  c.clearRect(0, 0, w, h);
  const axes = [["x", [1, 0, 0], "#ff6060"], ["y", [0, 1, 0], "#70e070"], ["z", [0, 0, 1], "#70a0ff"]];
  axes.sort((p, q) => dot(p[1], back) - dot(q[1], back));      // the farthest first
  c.lineWidth = 2; c.font = "bold 11px system-ui, sans-serif"; c.textAlign = "center"; c.textBaseline = "middle";
  for (const [name, v, colour] of axes) {
    const x = w / 2 + r * dot(v, right), y = h / 2 - r * dot(v, up);
    c.strokeStyle = colour; c.fillStyle = colour;
    c.beginPath(); c.moveTo(w / 2, h / 2); c.lineTo(x, y); c.stroke();
    c.fillText(name, w / 2 + 1.25 * (x - w / 2), h / 2 + 1.25 * (y - h / 2));
  }
}
