// omg serve's page: the form follows the chosen model's generation card (GET /v1/models); results play in a
// three.js skeleton viewer (bones from the parents the server sends, so any skeleton draws).
import * as THREE from 'three';
import { OrbitControls } from '/static/vendor/three/OrbitControls.js';

const $ = (id) => document.getElementById(id);
const COLORS = [0x1f77b4, 0xd62728, 0x2ca02c, 0x9467bd, 0xff7f0e, 0x17becf, 0x8c564b, 0xe377c2];
let models = [];
let current = null;
// read by the page's test: the frame shown, the frames drawn since the last result
const state = { motions: [], parents: [], frame: 0, frames: 0, fps: 20, playing: true, drawn: 0, results: 0 };
window.omgViewer = state;

function show(id, visible) { $(id).classList.toggle('hidden', !visible); }
function setStatus(text, error = false) { $('status').textContent = text; $('status').classList.toggle('error', error); }

async function loadModels() {
  const response = await fetch('/v1/models');
  models = (await response.json()).models;
  $('model').innerHTML = '';
  for (const m of models) $('model').add(new Option(`${m.name} (${m.card.family}, ${m.card.skeleton})`, m.name));
  onModel();
}

function onModel() {
  current = models.find((m) => m.name === $('model').value);
  const c = current.card;
  const takes = (what) => c.inputs.includes(what);
  show('text-box', takes('text'));
  show('unconditional-box', takes('text') && takes('unconditional'));
  $('unconditional').checked = false;
  $('prompts').disabled = false;
  show('upload-box', takes('motion'));
  show('species-box', takes('species'));
  show('length-box', !c.source_fixes_length);
  show('diffusion-box', c.samplers.length > 0);
  show('guidance-box', c.guidance !== null);
  $('examples').innerHTML = '';
  for (const text of current.examples) {
    const b = document.createElement('button');
    b.type = 'button'; b.textContent = text;
    b.onclick = () => { $('prompts').value = text; };
    $('examples').append(b);
  }
  $('species-list').innerHTML = '';
  for (const s of c.species) $('species-list').append(new Option(s));
  $('unconditional').onchange = () => { $('prompts').disabled = $('unconditional').checked; };
  $('sampler').innerHTML = '';
  for (const s of c.samplers) $('sampler').add(new Option(s, s));
  $('steps').placeholder = c.default_steps || '';
  $('steps').max = c.max_steps || '';
  $('guidance').placeholder = c.guidance ?? '';
  $('length').max = c.max_frames / c.fps;
  const inputs = c.inputs.map((i) => (c.needs.includes(i) ? `${i} (needed)` : i)).join(', ');
  $('card').textContent = `${c.family}: ${c.skeleton} at ${c.fps} fps, ${(c.min_frames / c.fps).toFixed(1)}–` +
    `${(c.max_frames / c.fps).toFixed(0)} s; takes ${inputs}`;
}

function number(id) { const v = $(id).value.trim(); return v === '' ? null : Number(v); }

async function generate() {
  const c = current.card;
  const unconditional = c.inputs.includes('unconditional') && (!c.inputs.includes('text') || $('unconditional').checked);
  const lines = unconditional || !c.inputs.includes('text') ? [] : $('prompts').value.split('\n');
  const prompts = lines.map((p) => p.trim()).filter(Boolean);  // blank lines only separate prompts
  const species = c.inputs.includes('species') ? $('species').value.trim() || null : null;
  const file = c.inputs.includes('motion') ? $('upload').files[0] : undefined;
  // an empty box is not a request for unconditional motion: that is the switch's (the API refuses an empty prompt)
  if (c.inputs.includes('text') && !unconditional && !file && !prompts.length) {
    setStatus(`write a prompt (one per line)${c.inputs.includes('unconditional') ? ', or tick unconditional' : ''}`,
              true);
    return;
  }
  let request;
  if (file) {
    const form = new FormData();
    form.append('file', file);
    form.append('model', current.name);
    if (species) form.append('to', species);
    for (const p of prompts) form.append('prompts', p);
    form.append('seed', $('seed').value || '0');
    form.append('num_samples', $('num_samples').value || '1');
    request = fetch('/v1/transfer', { method: 'POST', body: form });
  } else {
    const body = { model: current.name, prompts, num_samples: number('num_samples') ?? 1, seed: number('seed') ?? 0 };
    if (!c.source_fixes_length && number('length') !== null) body.length = number('length');
    if (c.samplers.length) { body.sampler = $('sampler').value; body.steps = number('steps'); }
    if (c.guidance !== null) body.guidance = number('guidance');
    if (species) body.species = species;
    request = fetch('/v1/generate', { method: 'POST', headers: { 'content-type': 'application/json' },
                                      body: JSON.stringify(body) });
  }
  $('generate').disabled = true;
  $('progress').removeAttribute('value');  // indeterminate until the sampler reports a step
  show('progress', true);
  let answered = false;  // a status poll still on its way must not overwrite the answer
  const poll = setInterval(async () => {  // progress: the sampler's step and the time left, by the server's clock
    try {
      const s = await (await fetch('/v1/status')).json();
      if (answered) return;
      setStatus(progressText(s));
    } catch (e) { /* the answer comes anyway */ }
  }, 250);
  try {
    const response = await request;
    const result = await response.json();
    answered = true;
    if (!response.ok) { setStatus(result.detail || `error ${response.status}`, true); return; }
    setStatus(`${result.motions.length} motion(s) in ${result.seconds} s` +
              (result.batched_motions > result.motions.length ? ` (sampled with ${result.batched_motions} others)` : ''));
    showResult(result);
  } catch (e) {
    answered = true;
    setStatus(`the server did not answer: ${e}`, true);
  } finally {
    clearInterval(poll);
    show('progress', false);
    $('generate').disabled = false;
  }
}

// "step 37 of 200, about 12 s left" (or "motion 2 of 4" for a model without sampler steps) from GET /v1/status
function progressText(s) {
  const p = s.progress;
  const queued = s.queued ? ` (${s.queued} requests queued)` : '';
  if (!p) return `waiting for the sampler…${queued}`;
  if (p.steps) { $('progress').max = p.steps; $('progress').value = p.step; }
  else { $('progress').max = p.motions; $('progress').value = p.done; }
  const at = p.steps ? `step ${p.step} of ${p.steps}` : `motion ${Math.min(p.done + 1, p.motions)} of ${p.motions}`;
  const t = Math.ceil(p.eta_s ?? 0);
  const left = p.eta_s === null ? '' : `, about ${t < 60 ? `${t} s` : `${Math.floor(t / 60)} min ${t % 60} s`} left`;
  return `sampling… ${at}${left}${queued}`;
}

// -- the viewer --------------------------------------------------------------------------------
const viewer = $('viewer');
const renderer = new THREE.WebGLRenderer({ antialias: true, preserveDrawingBuffer: true });
renderer.setPixelRatio(window.devicePixelRatio);
renderer.setClearColor(0xffffff);
viewer.append(renderer.domElement);
const scene = new THREE.Scene();
const camera = new THREE.PerspectiveCamera(45, 1, 0.01, 500);
camera.position.set(0, 2.5, 6);
const controls = new OrbitControls(camera, renderer.domElement);
controls.target.set(0, 0.9, 0);
scene.add(new THREE.GridHelper(40, 80, 0x999999, 0xdddddd));
let group = new THREE.Group();
scene.add(group);

function resize() {
  const { clientWidth: w, clientHeight: h } = viewer;
  renderer.setSize(w, h, false);
  camera.aspect = w / Math.max(h, 1);
  camera.updateProjectionMatrix();
}
new ResizeObserver(resize).observe(viewer);

function showResult(result) {
  scene.remove(group);
  group = new THREE.Group();
  scene.add(group);
  const parents = result.parents;
  const bones = parents.map((p, j) => [p, j]).filter(([p]) => p >= 0);
  // side by side: each motion starts at its own slot, as wide as the widest skeleton
  let size = 0.5;
  for (const m of result.motions) {
    for (const joint of m.joints[0]) size = Math.max(size, Math.abs(joint[1]) * 1.2, Math.abs(joint[0]) * 2);
  }
  state.motions = result.motions.map((m, i) => {
    const [x0, , z0] = m.joints[0][0];
    const offset = new THREE.Vector3((i - (result.motions.length - 1) / 2) * size * 1.5 - x0, 0, -z0);
    const color = COLORS[i % COLORS.length];
    const lines = new THREE.LineSegments(new THREE.BufferGeometry(), new THREE.LineBasicMaterial({ color }));
    lines.geometry.setAttribute('position', new THREE.Float32BufferAttribute(new Float32Array(bones.length * 6), 3));
    const points = new THREE.Points(new THREE.BufferGeometry(), new THREE.PointsMaterial({ color, size: 0.04 }));
    points.geometry.setAttribute('position', new THREE.Float32BufferAttribute(new Float32Array(parents.length * 3), 3));
    const path = m.joints.map((f) => new THREE.Vector3(f[0][0], 0.005, f[0][2]).add(offset));
    const trail = new THREE.Line(new THREE.BufferGeometry().setFromPoints(path),
                                 new THREE.LineBasicMaterial({ color, transparent: true, opacity: 0.5 }));
    for (const o of [lines, points, trail]) { o.position.copy(offset); group.add(o); }
    trail.position.set(0, 0, 0);
    return { ...m, lines, points };
  });
  state.frames = Math.max(...result.motions.map((m) => m.frames));
  state.fps = result.fps;
  state.parents = parents;
  state.frame = 0;
  state.drawn = 0;
  state.results += 1;
  $('scrubber').max = state.frames - 1;
  const width = size * 1.5 * result.motions.length;
  controls.target.set(0, size / 2, 0);
  camera.position.set(0, size * 1.5, Math.max(width, size * 3) * 1.2);
  listSamples(result);
}

function listSamples(result) {
  $('samples').innerHTML = '';
  result.motions.forEach((m, i) => {
    const div = document.createElement('div');
    div.className = 'sample';
    div.style.borderColor = `#${COLORS[i % COLORS.length].toString(16).padStart(6, '0')}`;
    const title = document.createElement('b');
    title.textContent = `${i + 1}. ${m.title}`;
    div.append(title);
    for (const [kind, url] of [...Object.entries(m.files), ['settings', result.settings]]) {
      const a = document.createElement('a');
      a.href = url; a.textContent = kind === 'settings' ? 'settings JSON' : kind === 'bvh' ? 'BVH' : `.${kind}.npy`;
      a.setAttribute('download', '');
      div.append(a);
    }
    $('samples').append(div);
  });
}

function pose(frame) {
  for (const m of state.motions) {
    const f = m.joints[Math.min(frame, m.frames - 1)];
    const line = m.lines.geometry.attributes.position;
    let k = 0;
    for (const [j, joint] of f.entries()) {
      m.points.geometry.attributes.position.setXYZ(j, ...joint);
      const parent = state.parents[j];
      if (parent < 0) continue;
      line.setXYZ(k++, ...f[parent]);
      line.setXYZ(k++, ...joint);
    }
    line.needsUpdate = true;
    m.points.geometry.attributes.position.needsUpdate = true;
  }
}

let last = performance.now();
let clock = 0;
function animate(now) {
  requestAnimationFrame(animate);
  const dt = (now - last) / 1000;
  last = now;
  if (state.frames > 0) {
    if (state.playing) {
      clock = (clock + dt * state.fps) % state.frames;
      state.frame = Math.floor(clock);
      $('scrubber').value = state.frame;
    }
    pose(state.frame);
    $('frame').textContent = `${state.frame + 1} / ${state.frames}`;
    state.drawn += 1;
  }
  controls.update();
  renderer.render(scene, camera);
}

$('model').onchange = onModel;
$('generate').onclick = generate;
$('play').onclick = () => { state.playing = !state.playing; $('play').textContent = state.playing ? 'Pause' : 'Play'; };
$('scrubber').oninput = () => { state.frame = Number($('scrubber').value); clock = state.frame; };
resize();
requestAnimationFrame(animate);
loadModels().catch((e) => setStatus(`could not list the models: ${e}`, true));
