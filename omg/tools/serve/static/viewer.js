// omg serve's 3D view: each motion drawn with solid bones (a cylinder per bone, a sphere per joint) from the
// joints and parents the server sends, so any skeleton draws; or, once a character is put onto the result
// (POST /v1/results/{id}/character), that file itself: a glTF character's mesh, or a BVH rig's bones, played by
// THREE.AnimationMixer from the file's own animation at the page's clock. Each motion has a label with its
// prompt above its head, and the camera follows the motions (unless told not to).
import * as THREE from 'three';
import { OrbitControls } from '/static/vendor/three/OrbitControls.js';
import { GLTFLoader } from '/static/vendor/three/loaders/GLTFLoader.js';
import { BVHLoader } from '/static/vendor/three/loaders/BVHLoader.js';
import { CSS2DObject, CSS2DRenderer } from '/static/vendor/three/renderers/CSS2DRenderer.js';

export const COLORS = [0x1f77b4, 0xd62728, 0x2ca02c, 0x9467bd, 0xff7f0e, 0x17becf, 0x8c564b, 0xe377c2];
const UP = new THREE.Vector3(0, 1, 0);
const LABEL_GAP = 0.15;  // m above the highest joint

// Bones as solid shapes: one instanced mesh of unit cylinders (each scaled and turned onto its bone) and one
// of spheres (the joints), moved by set(positions) every frame.
class SolidBones {
  constructor(parents, color, radius) {
    this.parents = parents;
    this.bones = parents.map((p, j) => [p, j]).filter(([p]) => p >= 0);
    const material = new THREE.MeshStandardMaterial({ color, roughness: 0.6 });
    this.sticks = new THREE.InstancedMesh(new THREE.CylinderGeometry(radius * 0.7, radius * 0.7, 1, 10), material,
                                          Math.max(this.bones.length, 1));
    this.balls = new THREE.InstancedMesh(new THREE.SphereGeometry(radius, 12, 8), material, parents.length);
    for (const mesh of [this.sticks, this.balls]) mesh.frustumCulled = false;  // their instances move
    this.object = new THREE.Group();
    this.object.add(this.sticks, this.balls);
    this.matrix = new THREE.Matrix4();
    this.turn = new THREE.Quaternion();
    this.middle = new THREE.Vector3();
    this.along = new THREE.Vector3();
  }

  set(positions) {  // positions: a Vector3 per joint, in the group's frame
    const m = this.matrix;
    positions.forEach((p, j) => this.balls.setMatrixAt(j, m.makeTranslation(p.x, p.y, p.z)));
    this.bones.forEach(([p, j], k) => {
      this.along.subVectors(positions[j], positions[p]);
      const length = this.along.length();
      this.turn.setFromUnitVectors(UP, length > 1e-9 ? this.along.divideScalar(length) : UP);
      this.middle.addVectors(positions[j], positions[p]).multiplyScalar(0.5);
      this.sticks.setMatrixAt(k, m.compose(this.middle, this.turn, new THREE.Vector3(1, Math.max(length, 1e-6), 1)));
    });
    this.balls.instanceMatrix.needsUpdate = true;
    this.sticks.instanceMatrix.needsUpdate = true;
  }
}

function label(text, color) {
  const div = document.createElement('div');
  div.className = 'label';
  div.textContent = text;
  div.style.borderColor = `#${color.toString(16).padStart(6, '0')}`;
  return new CSS2DObject(div);
}

// A motion as the server sent it: joints (T, J, 3) drawn at its slot.
class SkeletonActor {
  constructor(motion, parents, offset, color, radius) {
    this.motion = motion;
    this.bones = new SolidBones(parents, color, radius);
    this.object = new THREE.Group();
    this.object.position.copy(offset);
    const path = motion.joints.map((f) => new THREE.Vector3(f[0][0], 0.005, f[0][2]));
    this.trail = new THREE.Line(new THREE.BufferGeometry().setFromPoints(path),
                                new THREE.LineBasicMaterial({ color, transparent: true, opacity: 0.5 }));
    this.object.add(this.bones.object, this.trail);
    this.points = parents.map(() => new THREE.Vector3());
  }

  pose(frame) {
    const f = this.motion.joints[Math.min(frame, this.motion.frames - 1)];
    f.forEach((joint, j) => this.points[j].set(...joint));
    this.bones.set(this.points);
  }

  // the root's place and the highest joint's height, in the world
  where(root) {
    root.copy(this.points[0]).add(this.object.position);
    return Math.max(...this.points.map((p) => p.y)) + this.object.position.y;
  }
}

// A file the motion was written to (a glTF character or a BVH rig), playing the animation omg added to it.
class FileActor {
  constructor(scene, bones, clip, offset, color, radius, scale) {
    this.object = new THREE.Group();
    this.object.position.copy(offset);
    this.object.scale.setScalar(scale);
    this.object.add(scene);
    this.bones = bones;
    this.mixer = new THREE.AnimationMixer(scene);
    this.action = this.mixer.clipAction(clip);
    this.action.play();
    this.duration = clip.duration;
    this.root = bones.find((b) => !b.parent || !b.parent.isBone) || bones[0];
    this.meshes = [];
    scene.traverse((o) => { if (o.isMesh) { this.meshes.push(o); o.frustumCulled = false; } });
    this.drawn = null;
    if (!this.meshes.length) {  // a rig without a mesh: its bones as solid shapes
      const parents = bones.map((b) => bones.indexOf(b.parent));
      this.drawn = new SolidBones(parents, color, radius / scale);
      this.rig = new THREE.Group();  // in the file's units, beside its scene
      this.rig.add(this.drawn.object);
      this.object.add(this.rig);
      this.points = bones.map(() => new THREE.Vector3());
      this.inverse = new THREE.Matrix4();
    }
    this.world = new THREE.Vector3();
  }

  pose(seconds) {
    // the page's clock sets the time (no time of the mixer's own): paused, scrubbed and playing alike
    this.action.time = Math.min(seconds, this.duration);
    this.mixer.update(0);
    this.object.updateMatrixWorld(true);
    if (this.drawn) {
      this.inverse.copy(this.object.matrixWorld).invert();
      this.bones.forEach((b, j) => this.points[j].setFromMatrixPosition(b.matrixWorld).applyMatrix4(this.inverse));
      this.drawn.set(this.points);
    }
  }

  where(root) {
    root.setFromMatrixPosition(this.root.matrixWorld);
    let top = -Infinity;
    for (const b of this.bones) top = Math.max(top, this.world.setFromMatrixPosition(b.matrixWorld).y);
    return top;
  }
}

async function loadFile(url) {
  if (url.toLowerCase().endsWith('.bvh')) {
    const bvh = await new BVHLoader().loadAsync(url);
    const root = bvh.skeleton.bones[0];
    const scene = new THREE.Group();
    scene.add(root);
    return { scene, bones: bvh.skeleton.bones, clip: bvh.clip };
  }
  const gltf = await new GLTFLoader().loadAsync(url);
  const bones = [];
  gltf.scene.traverse((o) => { if (o.isBone) bones.push(o); });
  if (!gltf.animations.length || !bones.length) throw new Error(`${url.split('/').pop()} holds no animated skeleton`);
  // the motion is the animation omg added, the last: a character may come with animations of its own
  return { scene: gltf.scene, bones, clip: gltf.animations[gltf.animations.length - 1] };
}

// Whether WebGL here runs on a GPU: not where the browser draws it in software (no GPU, or one it does not trust),
// which it says by refusing a context that must not have a major performance caveat, or by the renderer it names
// (chromium's SwiftShader, Mesa's llvmpipe, Windows' basic renderer)
const SOFTWARE_RENDERER = /swiftshader|llvmpipe|softpipe|software|basic render/i;
function onGpu() {
  const canvas = document.createElement('canvas');
  if (!canvas.getContext('webgl2', { failIfMajorPerformanceCaveat: true })) return false;
  const gl = canvas.getContext('webgl2');
  const info = gl.getExtension('WEBGL_debug_renderer_info');
  const renderer = info ? String(gl.getParameter(info.UNMASKED_RENDERER_WEBGL)) : '';
  gl.getExtension('WEBGL_lose_context')?.loseContext();
  return !SOFTWARE_RENDERER.test(renderer);
}

export class Viewer {
  // state: the page's shared state (window.omgViewer); the viewer writes antialias, follow, center and target to it
  constructor(container, state) {
    this.container = container;
    this.state = state;
    // multisampling smooths the bones' edges on a GPU; a software renderer would shade each pixel four times over,
    // most of what the page costs while a motion plays there
    state.antialias = onGpu();
    this.renderer = new THREE.WebGLRenderer({ antialias: state.antialias, preserveDrawingBuffer: true });
    this.renderer.setPixelRatio(window.devicePixelRatio);
    this.renderer.setClearColor(0xffffff);
    container.append(this.renderer.domElement);
    this.labels = new CSS2DRenderer();
    this.labels.domElement.className = 'labels';
    container.append(this.labels.domElement);
    this.scene = new THREE.Scene();
    this.scene.add(new THREE.HemisphereLight(0xffffff, 0x888888, 2.0));
    const sun = new THREE.DirectionalLight(0xffffff, 1.5);
    sun.position.set(3, 6, 4);
    this.scene.add(sun);
    this.camera = new THREE.PerspectiveCamera(45, 1, 0.01, 500);
    this.camera.position.set(0, 2.5, 6);
    this.controls = new OrbitControls(this.camera, this.labels.domElement);
    this.controls.target.set(0, 0.9, 0);
    this.scene.add(new THREE.GridHelper(40, 80, 0x999999, 0xdddddd));
    this.group = new THREE.Group();
    this.scene.add(this.group);
    this.actors = [];  // the motions as drawn now: skeletons, or the files put onto a character
    this.skeletons = [];
    this.slots = [];  // each motion's offset in the world
    this.tags = [];  // each motion's label
    this.follow = true;
    this.center = null;  // the point followed, where it was last drawn
    this.root = new THREE.Vector3();
    this.sum = new THREE.Vector3();
    state.follow = true;
    new ResizeObserver(() => this.resize()).observe(container);
    this.resize();
  }

  resize() {
    const { clientWidth: w, clientHeight: h } = this.container;
    this.renderer.setSize(w, h, false);
    this.labels.setSize(w, h);
    this.camera.aspect = w / Math.max(h, 1);
    this.camera.updateProjectionMatrix();
    this.render();  // a resized canvas is blank until drawn, and an idle page draws only now and then (app.js)
  }

  render() {
    this.renderer.render(this.scene, this.camera);
    this.labels.render(this.scene, this.camera);
  }

  setFollow(on) {
    this.follow = on;
    this.state.follow = on;
    this.center = null;  // from where the motions are now: the camera does not jump
  }

  // a result's motions side by side, each at its own slot, as wide as the widest skeleton
  show(result) {
    this.scene.remove(this.group);
    this.group = new THREE.Group();
    this.scene.add(this.group);
    let size = 0.5;
    for (const m of result.motions) {
      for (const joint of m.joints[0]) size = Math.max(size, Math.abs(joint[1]) * 1.2, Math.abs(joint[0]) * 2);
    }
    this.size = size;
    this.slots = result.motions.map((m, i) => {
      const [x0, , z0] = m.joints[0][0];
      return new THREE.Vector3((i - (result.motions.length - 1) / 2) * size * 1.5 - x0, 0, -z0);
    });
    this.skeletons = result.motions.map((m, i) => {
      const actor = new SkeletonActor(m, result.parents, this.slots[i], COLORS[i % COLORS.length], size * 0.025);
      this.group.add(actor.object);
      return actor;
    });
    this.tags = result.motions.map((m, i) => {
      const tag = label(m.title, COLORS[i % COLORS.length]);
      this.group.add(tag);
      return tag;
    });
    this.actors = this.skeletons;
    this.fps = result.fps;
    this.state.characters = 0;
    const width = size * 1.5 * result.motions.length;
    this.controls.target.set(0, size / 2, 0);
    this.camera.position.set(0, size * 1.5, Math.max(width, size * 3) * 1.2);
    this.center = null;
  }

  // the files a character upload answered (one per motion, in order) in place of the skeletons
  async showFiles(urls) {
    const loaded = await Promise.all(urls.map(loadFile));
    const actors = loaded.map(({ scene, bones, clip }, i) => {
      scene.updateMatrixWorld(true);
      const height = Math.max(...bones.map((b) => new THREE.Vector3().setFromMatrixPosition(b.matrixWorld).y));
      const model = Math.max(...this.skeletons[i].motion.joints[0].map((j) => j[1]));
      // a BVH rig in its own unit (cm, inches): the nearest power of ten that makes it the motion's size
      const scale = urls[i].toLowerCase().endsWith('.bvh') && height > 0
        ? 10 ** Math.round(Math.log10(model / height)) : 1;
      return new FileActor(scene, bones, clip, this.slots[i], COLORS[i % COLORS.length], this.size * 0.025, scale);
    });
    for (const s of this.skeletons) s.object.visible = false;
    for (const a of this.actors) if (!this.skeletons.includes(a)) this.group.remove(a.object);
    for (const a of actors) this.group.add(a.object);
    this.actors = actors;
    this.state.characters = actors.filter((a) => a.meshes.length).length;
    this.center = null;
  }

  // back to the skeletons (the character cleared)
  showSkeletons() {
    for (const a of this.actors) if (!this.skeletons.includes(a)) this.group.remove(a.object);
    for (const s of this.skeletons) s.object.visible = true;
    this.actors = this.skeletons;
    this.state.characters = 0;
    this.center = null;
  }

  // whether what is drawn moves between whole frames: a character's animation interpolates, a skeleton does not
  interpolates() {
    return this.actors.some((actor, i) => actor !== this.skeletons[i]);
  }

  // clock: the page's playback time in frames (fractional while playing)
  draw(frame, clock) {
    if (this.actors.length) {
      this.sum.set(0, 0, 0);
      this.actors.forEach((actor, i) => {
        actor.pose(actor === this.skeletons[i] ? frame : clock / this.fps);
        const top = actor.where(this.root);
        this.sum.add(this.root);
        this.tags[i].position.set(this.root.x, top + LABEL_GAP * this.size / 1.2, this.root.z);
      });
      this.sum.divideScalar(this.actors.length);
      this.sum.y = 0;
      if (this.follow) {  // the camera moves with the motions' mean root, keeping its angle and distance
        if (this.center) {
          const moved = this.sum.clone().sub(this.center);
          this.camera.position.add(moved);
          this.controls.target.add(moved);
        }
        this.center = this.sum.clone();
      }
      this.state.center = this.sum.toArray();
      this.state.target = this.controls.target.toArray();
    }
    this.controls.update();
    this.render();
  }
}
