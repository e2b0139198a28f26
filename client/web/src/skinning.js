// The template mesh fitted to each avatar's calibrated skeleton, and its pose each frame
// (client/viewer/skinning.py, the desktop viewer's, in JS; pure maths, no three.js).
//
// The server's /avatar.json gives the mesh's *bind skeleton* (the rig with hips and knees
// where calibration puts every avatar's) in mesh joint order: names, parents, offsets,
// and bind_shift d_j = rest_j - bind_j. Per avatar, each joint gets a 3x3 map F_j in its
// bone's frame that carries the bind skeleton's child offsets onto the avatar's
// (regularised towards the avatar's body scale), so long arms are long, not fat. Each
// frame, forward kinematics on the avatar's own offsets gives R_j, p_j, and the flesh
// bound to joint j moves by A_j = [R_j F_j | p_j + R_j F_j d_j] (then the mesh's inverse
// bind matrix, which three.js applies). A_j is no rotation-translation-scale of a node
// tree: a stretch along a bone would shear that bone's children, so the page writes A_j
// as each bone's world matrix itself.

const FIT_LAMBDA = 1e-3; // skinning._FIT_LAMBDA

export class SkeletonMismatch extends Error {}

/** The /avatar.json document -> the bind skeleton (mesh joint order). */
export function bindSkeleton(doc) {
  const J = doc.joints.length;
  const flat = (rows) => Float64Array.from(rows.flat());
  const bind = { joints: doc.joints, parents: Int32Array.from(doc.parents),
    offsets: flat(doc.bind_offsets), shift: flat(doc.bind_shift),
    headTip: Float64Array.from(doc.head_tip), labelAbove: doc.label_above_head_m,
    children: Array.from({ length: J }, () => []) };
  bind.parents.forEach((p, j) => { if (j > 0) bind.children[p].push(j); });
  bind.head = doc.joints.indexOf("head");
  return bind;
}

/** An avatar (checked roster entry) fitted to the mesh; throws SkeletonMismatch when its
 * skeleton is not the mesh's rig (another joint's name, or another hierarchy). */
export function fitAvatar(bind, info) {
  const index = new Map(info.jointNames.map((name, i) => [name, i]));
  const missing = bind.joints.filter((name) => !index.has(name));
  if (missing.length) {
    throw new SkeletonMismatch(`avatar ${info.avatarId} (${info.displayName}): its skeleton ` +
      `lacks the mesh joints ${missing.slice(0, 5).join(", ")}`);
  }
  const J = bind.joints.length;
  const order = Int32Array.from(bind.joints, (name) => index.get(name));
  for (let j = 1; j < J; j++) {
    if (info.parents[order[j]] !== order[bind.parents[j]]) {
      throw new SkeletonMismatch(`avatar ${info.avatarId} (${info.displayName}): its joint ` +
        "hierarchy differs from the mesh's rig");
    }
  }
  const offsets = new Float64Array(3 * J);
  order.forEach((a, j) => offsets.set(info.restOffsets.subarray(3 * a, 3 * a + 3), 3 * j));
  const scale = bodyScale(bind.offsets, offsets);
  return { info, order, offsets, scale, fit: fitMatrices(bind, offsets, scale),
    jointCount: info.jointNames.length };
}

/** The median ratio of the avatar's bone lengths to the template's (skinning.body_scale). */
export function bodyScale(template, offsets) {
  const ratios = [];
  for (let j = 1; j < template.length / 3; j++) {
    const t = Math.hypot(template[3 * j], template[3 * j + 1], template[3 * j + 2]);
    if (t > 1e-6) ratios.push(Math.hypot(offsets[3 * j], offsets[3 * j + 1], offsets[3 * j + 2]) / t);
  }
  if (!ratios.length) return 1.0;
  ratios.sort((a, b) => a - b);
  const mid = ratios.length >> 1;
  return ratios.length % 2 ? ratios[mid] : (ratios[mid - 1] + ratios[mid]) / 2;
}

/** Per joint the 3x3 map (row-major, 9 numbers each) of skinning.fit_matrices:
 * F = (sum a t^T + lam s I) (sum t t^T + lam I)^-1 over the joint's children c. */
export function fitMatrices(bind, offsets, s) {
  const J = bind.joints.length;
  const fit = new Float64Array(9 * J);
  const t = bind.offsets;
  for (let j = 0; j < J; j++) {
    const kids = bind.children[j];
    if (!kids.length) {
      if (j > 0) fit.copyWithin(9 * j, 9 * bind.parents[j], 9 * bind.parents[j] + 9);
      else fit.set(scaled(identity(), s), 0);
      continue;
    }
    let lam = 0.0;
    for (const c of kids) for (let k = 0; k < 3; k++) lam += t[3 * c + k] ** 2;
    lam *= FIT_LAMBDA;
    if (lam <= 0.0) {
      fit.set(scaled(identity(), s), 9 * j);
      continue;
    }
    const lhs = scaled(identity(), lam * s);
    const rhs = scaled(identity(), lam);
    for (const c of kids) {
      for (let r = 0; r < 3; r++) {
        for (let k = 0; k < 3; k++) {
          lhs[3 * r + k] += offsets[3 * c + r] * t[3 * c + k];
          rhs[3 * r + k] += t[3 * c + r] * t[3 * c + k];
        }
      }
    }
    fit.set(multiply(lhs, inverse(rhs)), 9 * j);
  }
  return fit;
}

/** Forward kinematics in mesh order: local rotations (the avatar's joint order, 4 a
 * joint from `start` of `rotations`) and the root -> global rotations and positions. */
export function pose(bind, fitted, rotations, start, root) {
  const J = bind.joints.length;
  const gq = new Float64Array(4 * J);
  const gp = new Float64Array(3 * J);
  const local = (j) => rotations.subarray(4 * (start + fitted.order[j]), 4 * (start + fitted.order[j]) + 4);
  gq.set(local(0), 0);
  gp.set(root, 0);
  for (let j = 1; j < J; j++) {
    const p = bind.parents[j];
    const g = gq.subarray(4 * p, 4 * p + 4);
    gq.set(quatMultiply(g, local(j)), 4 * j);
    const t = quatRotate(g, fitted.offsets.subarray(3 * j, 3 * j + 3));
    for (let k = 0; k < 3; k++) gp[3 * j + k] = gp[3 * p + k] + t[k];
  }
  return { gq, gp };
}

/** A_j = [R_j F_j | p_j + R_j F_j d_j] of every joint, column-major 4x4 (16 numbers a
 * joint, three.js' Matrix4 layout): the bones' world matrices. */
export function boneMatrices(bind, fitted, posed, out = new Float64Array(16 * bind.joints.length)) {
  const J = bind.joints.length;
  for (let j = 0; j < J; j++) {
    const rf = multiply(quatMatrix(posed.gq.subarray(4 * j, 4 * j + 4)),
      fitted.fit.subarray(9 * j, 9 * j + 9));
    const d = bind.shift.subarray(3 * j, 3 * j + 3);
    const o = 16 * j;
    for (let r = 0; r < 3; r++) {
      for (let c = 0; c < 3; c++) out[o + 4 * c + r] = rf[3 * r + c];
      out[o + 3 * 4 + r] = posed.gp[3 * j + r] + rf[3 * r] * d[0] + rf[3 * r + 1] * d[1] +
        rf[3 * r + 2] * d[2];
      out[o + 4 * r + 3] = 0.0;
    }
    out[o + 15] = 1.0;
  }
  return out;
}

/** Where an avatar's name goes: above the top of its head (renderer.label_anchors). */
export function labelAnchor(bind, fitted, posed) {
  const h = bind.head;
  const f = fitted.fit.subarray(9 * h, 9 * h + 9);
  const tip = [0, 1, 2].map((r) => f[3 * r] * bind.headTip[0] + f[3 * r + 1] * bind.headTip[1] +
    f[3 * r + 2] * bind.headTip[2]);
  const t = quatRotate(posed.gq.subarray(4 * h, 4 * h + 4), tip);
  return [posed.gp[3 * h] + t[0], posed.gp[3 * h + 1] + t[1] + bind.labelAbove,
    posed.gp[3 * h + 2] + t[2]];
}

// ------------------------------------------------------------------ small maths
function identity() {
  return Float64Array.of(1, 0, 0, 0, 1, 0, 0, 0, 1);
}

function scaled(m, s) {
  return m.map((v) => v * s);
}

function multiply(a, b) {
  const out = new Float64Array(9);
  for (let r = 0; r < 3; r++) {
    for (let c = 0; c < 3; c++) {
      out[3 * r + c] = a[3 * r] * b[c] + a[3 * r + 1] * b[3 + c] + a[3 * r + 2] * b[6 + c];
    }
  }
  return out;
}

function inverse(m) {
  const [a, b, c, d, e, f, g, h, i] = m;
  const co = [e * i - f * h, c * h - b * i, b * f - c * e,
    f * g - d * i, a * i - c * g, c * d - a * f,
    d * h - e * g, b * g - a * h, a * e - b * d];
  const det = a * co[0] + b * co[3] + c * co[6];
  return Float64Array.from(co, (v) => v / det);
}

export function quatMultiply(a, b) {
  const [ax, ay, az, aw] = a;
  const [bx, by, bz, bw] = b;
  return [aw * bx + ax * bw + ay * bz - az * by, aw * by - ax * bz + ay * bw + az * bx,
    aw * bz + ax * by - ay * bx + az * bw, aw * bw - ax * bx - ay * by - az * bz];
}

export function quatRotate(q, v) {
  // v + 2 w (u x v) + 2 u x (u x v), u the vector part
  const [x, y, z, w] = q;
  const tx = 2 * (y * v[2] - z * v[1]);
  const ty = 2 * (z * v[0] - x * v[2]);
  const tz = 2 * (x * v[1] - y * v[0]);
  return [v[0] + w * tx + (y * tz - z * ty), v[1] + w * ty + (z * tx - x * tz),
    v[2] + w * tz + (x * ty - y * tx)];
}

function quatMatrix(q) {
  const [x, y, z, w] = q;
  return Float64Array.of(
    1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w),
    2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w),
    2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y));
}
