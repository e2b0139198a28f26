// The 3D view: each avatar a three.js SkinnedMesh (skinned on the GPU) sharing the
// MakeHuman geometry, its name and devices (how many, which are lost now) in an HTML
// label above its head, a floor grid and an orbit camera that frames the room until the
// spectator moves it.

import * as THREE from "three";
import { OrbitControls } from "three/addons/controls/OrbitControls.js";
import { CSS2DObject, CSS2DRenderer } from "three/addons/renderers/CSS2DRenderer.js";
import { deviceText } from "./devices.js";
import { boneMatrices, labelAnchor, pose } from "./skinning.js";

// the desktop viewer's colours (renderer.PALETTE, BACKGROUND), by avatar id
const PALETTE = [[0.90, 0.45, 0.25], [0.25, 0.60, 0.90], [0.45, 0.80, 0.35],
  [0.85, 0.35, 0.70], [0.95, 0.80, 0.30], [0.35, 0.85, 0.80], [0.65, 0.50, 0.90],
  [0.90, 0.55, 0.55]];
const BACKGROUND = [0.11, 0.12, 0.15];
const FOV_Y = 50;
const FRAMING_SMOOTHING = 0.15; // auto-framing moves this share of the way each frame
// the view holds every avatar, their names and a margin (the HUD covers a corner)
const FRAMING_MARGIN = 1.5;
const FRAMING_MIN_RADIUS_M = 1.2;

export function avatarColor(id) {
  return PALETTE[id % PALETTE.length];
}

export class Scene {
  /** `mesh`: the GLB's SkinnedMesh (geometry, skin joints, inverse binds); `bind`: the
   * bind skeleton of /avatar.json. */
  constructor(container, mesh, bind) {
    this.bind = bind;
    this.geometry = mesh.geometry;
    // skin joint i of the file is mesh joint skinToMesh[i] of /avatar.json
    const byName = new Map(bind.joints.map((name, j) => [name, j]));
    this.meshToSkin = new Int32Array(bind.joints.length);
    mesh.skeleton.bones.forEach((bone, i) => {
      if (!byName.has(bone.name)) throw new Error(`the mesh's joint ${bone.name} is not in /avatar.json`);
      this.meshToSkin[byName.get(bone.name)] = i;
    });
    this.boneInverses = mesh.skeleton.boneInverses;
    this.renderer = new THREE.WebGLRenderer({ antialias: true });
    this.renderer.setPixelRatio(window.devicePixelRatio);
    this.renderer.setClearColor(new THREE.Color().setRGB(...BACKGROUND, THREE.SRGBColorSpace));
    container.appendChild(this.renderer.domElement);
    this.labels = new CSS2DRenderer();
    this.labels.domElement.className = "labels";
    container.appendChild(this.labels.domElement);
    this.scene = new THREE.Scene();
    this.scene.add(new THREE.HemisphereLight(0xffffff, 0x444450, 1.6));
    const sun = new THREE.DirectionalLight(0xffffff, 2.0);
    sun.position.set(0.4, 0.9, 0.5);
    this.scene.add(sun);
    const grid = new THREE.GridHelper(20, 20, 0x5a5f6e, 0x33373f);
    this.scene.add(grid);
    this.camera = new THREE.PerspectiveCamera(FOV_Y, 1, 0.05, 200);
    this.camera.position.set(2.0, 2.5, 5.6); // the desktop viewer's orbit: yaw 20, pitch 15
    this.controls = new OrbitControls(this.camera, this.labels.domElement);
    this.controls.target.set(0, 1, 0);
    this.controls.enableDamping = true;
    this.autoFrame = true; // until the spectator takes the camera
    this.controls.addEventListener("start", () => { this.autoFrame = false; });
    this.avatars = new Map(); // avatar id -> {mesh, label, bones, fitted, devices, lost}
    this.resize(container);
    window.addEventListener("resize", () => this.resize(container));
  }

  resize(container) {
    const w = container.clientWidth || window.innerWidth;
    const h = container.clientHeight || window.innerHeight;
    this.renderer.setSize(w, h);
    this.labels.setSize(w, h);
    this.camera.aspect = w / h;
    this.camera.updateProjectionMatrix();
  }

  /** Add or refit an avatar (a FittedAvatar of skinning.js). */
  setAvatar(fitted) {
    this.removeAvatar(fitted.info.avatarId);
    const bones = this.bind.joints.map(() => new THREE.Bone());
    for (const bone of bones) bone.matrixWorldAutoUpdate = false; // written by draw()
    const skin = [...this.meshToSkin].map(() => null);
    this.meshToSkin.forEach((s, j) => { skin[s] = bones[j]; });
    const material = new THREE.MeshLambertMaterial({
      color: new THREE.Color().setRGB(...avatarColor(fitted.info.avatarId), THREE.SRGBColorSpace) });
    const mesh = new THREE.SkinnedMesh(this.geometry, material);
    mesh.bind(new THREE.Skeleton(skin, this.boneInverses.map((m) => m.clone())), new THREE.Matrix4());
    mesh.frustumCulled = false; // its bounds move with the pose; ~26k triangles are cheap
    mesh.visible = false; // until its first frame
    const div = document.createElement("div");
    div.className = "name";
    const who = Object.assign(document.createElement("span"), { className: "who",
      textContent: fitted.info.displayName }); // text, never markup: the name is a player's
    const devices = Object.assign(document.createElement("span"), { className: "devices" });
    div.append(who, devices);
    div.style.borderColor = `rgb(${avatarColor(fitted.info.avatarId).map((c) => Math.round(255 * c)).join(",")})`;
    div.dataset.avatarId = String(fitted.info.avatarId);
    const label = new CSS2DObject(div);
    label.center.set(0.5, 1.0); // the label's bottom middle sits on the anchor
    label.visible = false;
    this.scene.add(mesh, label);
    this.avatars.set(fitted.info.avatarId, { mesh, label, bones, fitted, devices,
      lost: -1, matrices: new Float64Array(16 * bones.length), posed: null });
    this.setLost(fitted.info.avatarId, 0);
  }

  /** Which of avatar `id`'s devices its newest frame lacked (protocol.roles bits): the
   * line under its name changes only when they do (16 avatars, every frame). */
  setLost(id, bits) {
    const a = this.avatars.get(id);
    if (!a || a.lost === bits) return;
    a.lost = bits;
    const text = deviceText(a.fitted.info.devices, bits);
    a.devices.textContent = text;
    a.devices.hidden = !text;
    a.devices.classList.toggle("lost", bits !== 0);
  }

  removeAvatar(id) {
    const a = this.avatars.get(id);
    if (!a) return;
    this.scene.remove(a.mesh, a.label);
    a.label.element.remove();
    a.mesh.material.dispose();
    a.mesh.skeleton.dispose();
    this.avatars.delete(id);
  }

  /** Pose avatar `id` from its newest frame: rotations of the batch from joint `start`. */
  poseAvatar(id, rotations, start, root) {
    const a = this.avatars.get(id);
    if (!a) return;
    a.posed = pose(this.bind, a.fitted, rotations, start, root);
    boneMatrices(this.bind, a.fitted, a.posed, a.matrices);
    a.bones.forEach((bone, j) => bone.matrixWorld.fromArray(a.matrices, 16 * j));
    a.label.position.fromArray(labelAnchor(this.bind, a.fitted, a.posed));
    a.mesh.visible = a.label.visible = true;
  }

  render() {
    if (this.autoFrame) this.frameAvatars();
    this.controls.update();
    this.renderer.render(this.scene, this.camera);
    this.labels.render(this.scene, this.camera);
  }

  /** Aim at and back off to see every avatar (OrbitCamera.frame), eased. */
  frameAvatars() {
    const box = new THREE.Box3();
    for (const a of this.avatars.values()) {
      if (!a.posed) continue;
      for (let j = 0; j < a.posed.gp.length; j += 3) {
        box.expandByPoint(new THREE.Vector3().fromArray(a.posed.gp, j));
      }
      box.expandByPoint(a.label.position);
    }
    if (box.isEmpty()) return;
    const centre = box.getCenter(new THREE.Vector3());
    const radius = Math.max(0.5 * box.getSize(new THREE.Vector3()).length(), FRAMING_MIN_RADIUS_M);
    const distance = FRAMING_MARGIN * radius / Math.sin(THREE.MathUtils.degToRad(FOV_Y) / 2);
    const direction = this.camera.position.clone().sub(this.controls.target).normalize();
    this.controls.target.lerp(centre, FRAMING_SMOOTHING);
    const now = this.camera.position.distanceTo(this.controls.target);
    this.camera.position.copy(this.controls.target).addScaledVector(direction,
      now + FRAMING_SMOOTHING * (distance - now));
  }
}
