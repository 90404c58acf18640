// omg serve's page: the form follows the chosen model's generation card (GET /v1/models); results play in the
// three.js viewer of static/viewer.js, on the skeleton the server sends or on a character the user uploads.
import { COLORS, Viewer } from '/static/viewer.js';
import { createControl, limit } from '/static/control.js';

const $ = (id) => document.getElementById(id);
let models = [];
let current = null;
// read by the page's test: the frame shown, the frames drawn since the last result, every drawing since the start,
// how often the frame shown changed
const state = { motions: [], parents: [], frame: 0, frames: 0, fps: 20, playing: true, drawn: 0, results: 0, draws: 0,
  shownFrames: 0 };
window.omgViewer = state;

function show(id, visible) { $(id).classList.toggle('hidden', !visible); }
function setStatus(text, error = false) { $('status').textContent = text; $('status').classList.toggle('error', error); }

async function loadModels() {
  const response = await fetch('/v1/models');
  const answer = await response.json();
  models = answer.models;
  // the rigs this server reads, and a joint map (YAML) chosen with one whose names no built-in map fits
  $('character').accept = [...answer.limits.character_suffixes, '.yaml', '.yml'].join(',');
  $('character-kinds').textContent = answer.limits.character_suffixes.join(', ');
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
  show('smoothing-box', 'smoothing' in c.options);  // sampling's smoothing, where the card lists it
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
  // the number fields' bounds and defaults as the card lists them (its `ranges`): the server's, not the page's
  for (const name of ['steps', 'guidance', 'smoothing']) limit($(name), c.ranges[name]);
  $('length').min = c.min_frames / c.fps;
  $('length').max = c.max_frames / c.fps;
  const inputs = c.inputs.map((i) => (c.needs.includes(i) ? `${i} (needed)` : i)).join(', ');
  $('card').textContent = `${c.family}: ${c.skeleton} at ${c.fps} fps, ${(c.min_frames / c.fps).toFixed(1)}–` +
    `${(c.max_frames / c.fps).toFixed(0)} s; takes ${inputs}`;
  control.onModel(current);
}

function number(id) { const v = $(id).value.trim(); return v === '' ? null : Number(v); }

async function generate() {
  const c = current.card;
  const unconditional = c.inputs.includes('unconditional') && (!c.inputs.includes('text') || $('unconditional').checked);
  const timeline = !unconditional && control.hasTimeline();  // its segments' texts are the prompts
  const lines = unconditional || timeline || !c.inputs.includes('text') ? [] : $('prompts').value.split('\n');
  const prompts = lines.map((p) => p.trim()).filter(Boolean);  // blank lines only separate prompts
  const species = c.inputs.includes('species') ? $('species').value.trim() || null : null;
  const file = c.inputs.includes('motion') ? $('upload').files[0] : undefined;
  // an empty box is not a request for unconditional motion: that is the switch's (the API refuses an empty prompt)
  if (c.inputs.includes('text') && !unconditional && !file && !timeline && !prompts.length) {
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
    if ('smoothing' in c.options && number('smoothing') !== null) body.smoothing = number('smoothing');
    if (species) body.species = species;
    control.apply(body, timeline);
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
    if ($('character').files.length) await putOnCharacter();
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

// -- the viewer (static/viewer.js) and the results' list -------------------------------------------
const viewer = new Viewer($('viewer'), state);
// the control panel draws in the viewer's scene; clicks reach the label layer on top of the canvas
const control = createControl({ scene: viewer.scene, camera: viewer.camera, canvas: viewer.labels.domElement, $ });
window.omgControl = control.debug;
let shown = null;  // the result in the view

function showResult(result) {
  shown = result;
  viewer.show(result);
  state.motions = result.motions;
  state.frames = Math.max(...result.motions.map((m) => m.frames));
  state.fps = result.fps;
  state.parents = result.parents;
  state.frame = 0;
  state.drawn = 0;
  state.results += 1;
  $('scrubber').max = state.frames - 1;
  listSamples(result);
  control.showResult(result, result.motions.map((m, i) => ({ ...m, offset: viewer.slots[i] })), viewer.group);
}

// the shown result's motions on the character chosen (POST /v1/results/{id}/character): the files to download,
// played in the view on the character's mesh; no character chosen: the skeletons again
async function putOnCharacter() {
  const chosen = [...$('character').files];
  const map = chosen.find((f) => /\.ya?ml$/i.test(f.name));  // its joint map, chosen with it
  const file = chosen.find((f) => f !== map);
  const result = shown;
  if (!result) return;
  if (!file) { result.character = null; viewer.showSkeletons(); listSamples(result); return; }
  const form = new FormData();
  form.append('file', file);
  if (map) form.append('joint_map_file', map);
  const said = $('status').textContent.split('; ')[0];
  setStatus(`${said}; putting the motions onto ${file.name}…`);
  try {
    const response = await fetch(`/v1/results/${result.id}/character`, { method: 'POST', body: form });
    const answer = await response.json();
    if (result !== shown) return;  // a newer result is in the view
    if (!response.ok) { setStatus(answer.detail || `error ${response.status}`, true); return; }
    const urls = answer.motions.map((m) => m.url);  // the downloads: the character's own format
    const views = answer.motions.map((m) => m.view);  // what the view plays (an FBX character's .glb)
    const playable = views.every((u) => /\.(glb|bvh)$/i.test(u));  // what the viewer's loaders read
    if (playable) await viewer.showFiles(views);
    result.character = { name: answer.character, urls };
    listSamples(result);
    setStatus(`${said}; on ${answer.character} in ${answer.seconds} s` +
              (playable ? '' : ' (the view plays .glb and .bvh files: download it)'));
  } catch (e) {
    setStatus(`could not show ${file.name}: ${e}`, true);
  }
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
      a.href = url;
      a.textContent = { settings: 'settings JSON', bvh: 'BVH', glb: 'glTF' }[kind] ?? `.${kind}.npy`;
      a.setAttribute('download', '');
      div.append(a);
    }
    if (result.character) {
      const a = document.createElement('a');
      a.href = result.character.urls[i]; a.textContent = `on ${result.character.name}`;
      a.className = 'character';
      a.setAttribute('download', '');
      div.append(a);
    }
    $('samples').append(div);
  });
}

// Drawing the scene is what the page costs while nothing moves (a software renderer's CPU, a laptop's battery).
// A skeleton shows whole frames, so while skeletons play it is drawn when the frame changes (a 20-fps motion:
// 20 draws a second, not the display's 60); a character interpolates between frames and is drawn on every
// animation frame. For ACTIVE_MS after the user did anything it is drawn on every animation frame (the camera
// glides), and otherwise IDLE_DRAW_MS apart, which still shows within a moment what an answer or a loaded file
// changed in the scene
const ACTIVE_MS = 1000;
const IDLE_DRAW_MS = 250;
let activeUntil = 0;
let lastDraw = -Infinity;
let lastFrame = -1;
for (const kind of ['pointerdown', 'pointermove', 'pointerup', 'wheel', 'keydown', 'input', 'change', 'resize']) {
  window.addEventListener(kind, () => { activeUntil = performance.now() + ACTIVE_MS; }, { capture: true, passive: true });
}

let last = performance.now();
let clock = 0;
function animate(now) {
  requestAnimationFrame(animate);
  const dt = (now - last) / 1000;
  last = now;
  const playing = state.frames > 0 && state.playing;
  if (playing) {
    clock = (clock + dt * state.fps) % state.frames;
    state.frame = Math.floor(clock);
  }
  // a new result is drawn at once; a playing one when its frame changes, or always where it interpolates
  const moves = (state.frames > 0 && state.drawn === 0)
    || (playing && (state.frame !== lastFrame || viewer.interpolates()));
  if (!moves && now > activeUntil && now - lastDraw < IDLE_DRAW_MS) return;
  lastDraw = now;
  state.draws += 1;
  if (state.frames > 0) {
    if (state.frame !== lastFrame) state.shownFrames += 1;
    lastFrame = state.frame;
    if (state.playing) $('scrubber').value = state.frame;
    $('frame').textContent = `${state.frame + 1} / ${state.frames}`;
    state.drawn += 1;
  }
  viewer.draw(state.frame, state.playing ? clock : state.frame);
}

$('model').onchange = onModel;
$('character').onchange = putOnCharacter;
$('follow').onchange = () => viewer.setFollow($('follow').checked);
$('generate').onclick = generate;
$('play').onclick = () => { state.playing = !state.playing; $('play').textContent = state.playing ? 'Pause' : 'Play'; };
$('scrubber').oninput = () => { state.frame = Number($('scrubber').value); clock = state.frame; };
requestAnimationFrame(animate);
loadModels().catch((e) => setStatus(`could not list the models: ${e}`, true));
