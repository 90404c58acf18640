// The page's Control panel: a root path drawn on the ground grid, keyframes taken from a frame of an uploaded take,
// a prompt timeline and a body-part composition (sampled in one chain or in separate chains). The request carries them as `constraints` and `timeline` in the documented JSON format
// (docs/guide/control.md, docs/guide/timelines.md); the chosen model's card decides what the panel offers. The
// viewer shows the constraints beside each motion (markers at the targets, the path as a line on the ground) and
// each motion's control error from its record.
import * as THREE from 'three';

const EDIT = 0xff7f0e;  // what is being drawn
const MARK = 0x111111;  // the constraints a result was generated with
const CLICK_PX = 5;  // a pointer that moved further between down and up dragged the view: no point

const round = (v, digits) => Number(v.toFixed(digits));

function element(tag, props = {}, children = []) {
  const e = Object.assign(document.createElement(tag), props);
  e.append(...children);
  return e;
}

// A number field's bounds and placeholder from a range the server lists (GET /v1/models: a card's `ranges`, a
// model's `timeline_ranges`): `show` words the default (null: none); no range, no bounds.
export function limit(input, range, show = (value) => value ?? '') {
  input.min = range?.low ?? '';
  input.max = range?.high ?? '';
  input.placeholder = range ? show(range.default) : '';
}

function button(text, onclick, id) {
  const b = element('button', { type: 'button', textContent: text, onclick });
  if (id) b.id = id;
  return b;
}

function sphere(position, radius, color, kind) {
  const mesh = new THREE.Mesh(new THREE.SphereGeometry(radius, 10, 8), new THREE.MeshBasicMaterial({ color }));
  mesh.position.set(...position);
  mesh.userData.control = kind;
  return mesh;
}

function groundLine(points, color, kind) {  // points: [[x, z], ...] drawn just above the grid
  const vertices = points.map(([x, z]) => new THREE.Vector3(x, 0.01, z));
  const line = new THREE.Line(new THREE.BufferGeometry().setFromPoints(vertices),
                              new THREE.LineBasicMaterial({ color }));
  line.userData.control = kind;
  return line;
}

function bones(pose, parents, color, kind) {
  const segments = [];
  parents.forEach((p, j) => {
    if (p >= 0) segments.push(new THREE.Vector3(...pose[p]), new THREE.Vector3(...pose[j]));
  });
  const lines = new THREE.LineSegments(new THREE.BufferGeometry().setFromPoints(segments),
                                       new THREE.LineBasicMaterial({ color, transparent: true, opacity: 0.6 }));
  lines.userData.control = kind;
  return lines;
}

// The constraints' objects for one motion: the path (or waypoints) as a line from the start, keyframe joints and
// targets as markers at their positions. Targets on some axes only have no single point: they are not drawn.
function constraintObjects(constraints, parents, color) {
  const out = [];
  const ground = constraints.path ? constraints.path.points
    : constraints.waypoints ? [[0, 0], ...constraints.waypoints.map((w) => w.position)] : null;
  if (ground) {
    out.push(groundLine(ground, color, 'path'));
    for (const [x, z] of ground.slice(1)) out.push(sphere([x, 0.01, z], 0.03, color, 'waypoint'));
  }
  for (const k of constraints.keyframes || []) {
    const pose = k.positions || Object.values(k.joints || {});
    for (const p of pose) out.push(sphere(p, 0.025, color, 'keyframe'));
    if (k.positions && parents.length === k.positions.length) {
      out.push(bones(k.positions, parents, color, 'keyframe-bones'));
    }
  }
  for (const t of constraints.targets || []) {
    if ((t.axes || 'xyz').length === 3) out.push(sphere(t.position, 0.03, color, 'target'));
  }
  return out;
}

export function createControl({ scene, camera, canvas, $ }) {
  const state = { model: null, path: [], pathKind: 'path', take: null, keyframes: [], timeline: [], parts: [],
                  sent: null };
  const editing = new THREE.Group();  // the path and the keyframe being chosen, in the model's world
  scene.add(editing);

  // -- the panel ------------------------------------------------------------------------------------------------
  const why = element('div', { id: 'control-why', className: 'note' });
  const pathKind = element('select', { id: 'path-kind' });
  const pathInfo = element('span', { id: 'path-info', className: 'note' });
  const draw = button('Draw on the ground', () => {
    draw.classList.toggle('on');
    draw.textContent = draw.classList.contains('on') ? 'Drawing: click the grid' : 'Draw on the ground';
  }, 'path-draw');
  // with a path or keyframes the root moves at their pace, not the legs': held feet keep them from sliding
  const feet = element('input', { id: 'hold-feet', type: 'checkbox', checked: true });
  const feetLabel = element('label', { id: 'hold-feet-label' }, [feet, ' hold the feet still where they land']);
  const pathBox = element('fieldset', { id: 'path-box' }, [
    element('legend', { textContent: 'Root path' }),
    element('div', { className: 'note',
                     textContent: 'click points on the ground grid; the motion starts at the origin' }),
    draw, element('label', {}, ['Timing ', pathKind]), feetLabel,
    element('div', { className: 'buttons' }, [
      button('Undo', () => { state.path.pop(); redraw(); }, 'path-undo'),
      button('Clear', () => { state.path = []; redraw(); }, 'path-clear')]),
    pathInfo]);
  pathKind.onchange = () => { state.pathKind = pathKind.value; redraw(); };

  const takeFile = element('input', { id: 'keyframe-file', type: 'file', accept: '.bvh,.npy,.json,.txt,.amc,.asf' });
  const frame = element('input', { id: 'keyframe-frame', type: 'number', min: 0, value: 0, step: 1 });
  const time = element('input', { id: 'keyframe-time', type: 'number', min: 0, value: 0, step: 0.1 });
  const takeInfo = element('div', { id: 'keyframe-info', className: 'note' });
  const keyList = element('div', { id: 'keyframe-list' });
  const add = button('Add keyframe', addKeyframe, 'keyframe-add');
  const keyBox = element('fieldset', { id: 'keyframe-box' }, [
    element('legend', { textContent: 'Keyframes from a take' }),
    element('label', {}, ['Take ', element('small', { textContent: '(BVH, DeepMimic or .npy)' }), takeFile]),
    takeInfo,
    element('div', { className: 'row' }, [element('label', {}, ['Frame of the take', frame]),
                                          element('label', {}, ['At time (s)', time])]),
    add, keyList]);
  takeFile.onchange = readTake;
  frame.oninput = redraw;

  const rows = element('div', { id: 'timeline-rows' });
  // the timeline file's transition and context, for the segments and the body parts alike; an empty field is the
  // file's default and is not sent (their bounds and defaults: the model's timeline_ranges, set in onModel)
  const transition = element('input', { id: 'timeline-transition', type: 'number', step: 0.1,
                                        title: 'seconds over which two segments that only touch cross over, ' +
                                        'centred on their boundary; a body part with a start or end crosses in ' +
                                        'and out over it too (empty: the default shown)' });
  const context = element('input', { id: 'timeline-context', type: 'number', step: 0.1,
                                     title: 'seconds each text\u2019s denoiser sees on either side of its own ' +
                                     'frames, for segments and body parts (0: its own frames and crossings only; ' +
                                     'empty: the whole motion, the default)' });
  const timeBox = element('fieldset', { id: 'timeline-box' }, [
    element('legend', { textContent: 'Prompt timeline' }),
    element('div', { className: 'note', textContent: 'segments in seconds, each meeting or overlapping the next; ' +
                                                      'their texts replace the prompts, the last end sets the length' }),
    rows, button('Add segment', () => addSegment(), 'timeline-add'),
    element('div', { className: 'timing' }, [element('label', {}, ['transition (s) ', transition]),
                                             element('label', {}, ['context (s) ', context])])]);

  // body parts that follow their own text at the same time, and how the texts are sampled: one chain of blended
  // estimates (the default) or separate chains pulled together by the coupling (the timeline file's chains)
  const partRows = element('div', { id: 'parts-rows' });
  const partNames = element('div', { id: 'parts-names', className: 'note' });
  const separate = element('input', { id: 'parts-separate', type: 'checkbox' });
  const coupling = element('input', { id: 'parts-coupling', type: 'number', step: 0.05, disabled: true,
                                      title: 'each chain\u2019s pull towards the composed motion (empty: the ' +
                                      'default shown)' });
  separate.onchange = () => { coupling.disabled = !separate.checked; };
  const partsBox = element('fieldset', { id: 'parts-box' }, [
    element('legend', { textContent: 'Body-part composition' }), partNames, partRows,
    button('Add part', () => addPart(), 'parts-add'),
    element('div', { className: 'chains' }, [
      element('label', { className: 'toggle', title: 'each text samples its own chain (body-part compositions ' +
                                                     'pass both parts more often)' }, [separate, ' separate chains']),
      element('label', { className: 'toggle' }, ['coupling ', coupling])])]);

  const panel = element('details', { id: 'control', open: true }, [element('summary', { textContent: 'Control' }),
                                                                   why, pathBox, keyBox, timeBox, partsBox]);
  $('control-box').append(panel);

  // -- the path: clicks on the ground plane ---------------------------------------------------------------------
  let down = null;
  canvas.addEventListener('pointerdown', (e) => { down = [e.clientX, e.clientY]; });
  canvas.addEventListener('pointerup', (e) => {
    if (!draw.classList.contains('on') || pathBox.disabled || !down) return;
    if (Math.hypot(e.clientX - down[0], e.clientY - down[1]) > CLICK_PX) return;
    const rect = canvas.getBoundingClientRect();
    const ndc = new THREE.Vector2(((e.clientX - rect.left) / rect.width) * 2 - 1,
                                  -((e.clientY - rect.top) / rect.height) * 2 + 1);
    const ray = new THREE.Raycaster();
    camera.updateMatrixWorld();
    ray.setFromCamera(ndc, camera);
    const hit = ray.ray.intersectPlane(new THREE.Plane(new THREE.Vector3(0, 1, 0), 0), new THREE.Vector3());
    if (!hit) return;  // above the horizon
    state.path.push([round(hit.x, 3), round(hit.z, 3)]);
    redraw();
  });

  // -- keyframes: the server retargets the take (/v1/keyframes), the page picks a frame -------------------------
  async function readTake() {
    const file = takeFile.files[0];
    state.take = null;
    redraw();
    if (!file) return;
    takeInfo.textContent = `reading ${file.name}…`;
    takeInfo.classList.remove('error');
    const form = new FormData();
    form.append('file', file);
    form.append('model', state.model.name);
    try {
      const response = await fetch('/v1/keyframes', { method: 'POST', body: form });
      const answer = await response.json();
      if (!response.ok) throw new Error(answer.detail || `error ${response.status}`);
      state.take = answer;
      frame.max = answer.frames - 1;
      frame.value = Math.min(Number(frame.value) || 0, answer.frames - 1);
      takeInfo.textContent = `${answer.source}: ${answer.frames} frames at ${answer.fps} fps on ${answer.skeleton}`;
    } catch (e) {
      takeInfo.textContent = String(e.message || e);
      takeInfo.classList.add('error');
    }
    redraw();
  }

  function addKeyframe() {
    if (!state.take) { takeInfo.textContent = 'upload a take first'; takeInfo.classList.add('error'); return; }
    const f = Math.max(0, Math.min(Math.round(Number(frame.value) || 0), state.take.frames - 1));
    state.keyframes.push({ time: Number(time.value) || 0, positions: state.take.poses[f],
                           label: `${state.take.source} frame ${f}` });
    redraw();
  }

  // -- the timeline -------------------------------------------------------------------------------------------
  function addSegment(segment) {
    const last = state.timeline[state.timeline.length - 1];
    const start = last ? last.end : 0;
    state.timeline.push(segment || { start, end: start + 2, text: '' });
    listSegments();
  }

  function listSegments() {
    rows.innerHTML = '';
    state.timeline.forEach((s, i) => {
      const field = (key, type) => {
        const input = element('input', { type, value: s[key], className: `segment-${key}` });
        if (type === 'number') { input.step = 0.1; input.min = 0; }
        input.oninput = () => { s[key] = type === 'number' ? Number(input.value) : input.value; };
        return input;
      };
      rows.append(element('div', { className: 'segment' }, [
        field('start', 'number'), field('end', 'number'), field('text', 'text'),
        button('×', () => { state.timeline.splice(i, 1); listSegments(); })]));
    });
  }

  // -- the body-part composition: rows of part names (space or comma separated), text, optional start and end --
  function addPart() {
    state.parts.push({ parts: '', text: '', start: '', end: '' });
    listParts();
  }

  function listParts() {
    partRows.innerHTML = '';
    state.parts.forEach((p, i) => {
      const field = (key, type, placeholder) => {
        const input = element('input', { type, value: p[key], placeholder, className: `part-${key}` });
        if (type === 'number') { input.step = 0.1; input.min = 0; }
        input.oninput = () => { p[key] = input.value; };
        return input;
      };
      partRows.append(element('div', { className: 'part' }, [
        field('parts', 'text', 'legs root'), field('start', 'number', 'start'), field('end', 'number', 'end'),
        button('×', () => { state.parts.splice(i, 1); listParts(); }), field('text', 'text', 'its text')]));
    });
  }

  // The timeline as the API takes it: the bare list of segments, or with parts, a transition or context given or
  // separate chains the mapping {timeline, parts, transition, context, chains, coupling}; a part without start or
  // end holds from the motion's start or to its end.
  function timelineBody() {
    const segments = timeBox.disabled ? [] : state.timeline.map(({ start, end, text }) => ({ start, end, text }));
    const parts = partsBox.disabled ? [] : state.parts.map((p) => ({
      parts: p.parts.split(/[\s,]+/).filter(Boolean), text: p.text,
      ...(p.start === '' ? {} : { start: Number(p.start) }), ...(p.end === '' ? {} : { end: Number(p.end) }) }));
    const timing = {};
    if (!timeBox.disabled) {
      for (const [key, input] of [['transition', transition], ['context', context]]) {
        if (input.value.trim() !== '') timing[key] = Number(input.value);
      }
    }
    const split = !partsBox.disabled && separate.checked;
    if (!parts.length && !split && !Object.keys(timing).length) return segments;
    const out = {};
    if (segments.length) out.timeline = segments;
    if (parts.length) out.parts = parts;
    Object.assign(out, timing);
    if (split) {
      out.chains = 'separate';
      if (coupling.value.trim() !== '') out.coupling = Number(coupling.value);
    }
    return out;
  }

  // -- what is drawn while editing --------------------------------------------------------------------------
  function redraw() {
    editing.clear();
    editing.visible = true;  // hidden while a result shows what it was generated with
    const constraints = current();
    if (constraints) for (const o of constraintObjects(constraints, state.model?.parents || [], EDIT)) editing.add(o);
    if (state.take) {  // the frame being chosen
      const f = Math.max(0, Math.min(Math.round(Number(frame.value) || 0), state.take.frames - 1));
      for (const o of constraintObjects({ keyframes: [{ positions: state.take.poses[f] }] }, state.model.parents,
                                        0x888888)) { o.userData.control = 'take'; editing.add(o); }
    }
    const n = state.path.length;
    pathInfo.textContent = n ? `${n} point(s), sent as ${state.pathKind === 'path' ? 'a dense path over the whole ' +
      'motion' : 'waypoints timed by the share of the path\u2019s length'}` : 'no path';
    keyList.innerHTML = '';
    state.keyframes.forEach((k, i) => keyList.append(element('div', { className: 'keyframe' }, [
      element('span', { textContent: `at ${k.time} s: ${k.label}` }),
      button('×', () => { state.keyframes.splice(i, 1); redraw(); })])));
  }

  // The constraints as the documented JSON, or null: a dense path starts at the origin, where the motion does.
  function current() {
    const kinds = state.model?.card.constraints || [];
    const out = {};
    if (state.path.length && kinds.includes(state.pathKind)) {
      if (state.pathKind === 'path') out.path = { points: [[0, 0], ...state.path] };
      else out.waypoints = state.path.map((position) => ({ position }));
    }
    if (state.keyframes.length && kinds.includes('keyframes')) {
      out.keyframes = state.keyframes.map((k) => ({ time: k.time, positions: k.positions }));
    }
    // enabled only for a card that lists the feet it holds (onModel)
    if (Object.keys(out).length && feet.checked && !feet.disabled) out.contacts = [...state.model.card.contacts];
    return Object.keys(out).length ? out : null;
  }

  return {
    onModel(model) {
      const skeletonChanged = state.model && state.model.card.skeleton !== model.card.skeleton;
      state.model = model;
      const c = model.card;
      if (skeletonChanged) { state.keyframes = []; state.take = null; takeFile.value = ''; takeInfo.textContent = ''; }
      pathKind.innerHTML = '';
      for (const k of ['path', 'waypoints']) if (c.constraints.includes(k)) pathKind.add(new Option(k, k));
      if (pathKind.options.length) {
        pathKind.value = c.constraints.includes(state.pathKind) ? state.pathKind : pathKind.options[0].value;
      }
      state.pathKind = pathKind.value;
      pathBox.disabled = !pathKind.options.length;
      feet.disabled = !c.constraints.includes('contacts') || !(c.contacts || []).length;
      feetLabel.title = feet.disabled ? 'this model holds no feet' : `contacts: ${c.contacts.join(', ')}`;
      keyBox.disabled = !c.constraints.includes('keyframes');
      timeBox.disabled = !c.timeline.includes('timeline');
      partsBox.disabled = !c.timeline.includes('parts');
      const ranges = model.timeline_ranges;
      limit(transition, ranges.transition, (value) => `${value} (default)`);
      limit(context, ranges.context, (value) => value ?? 'whole motion');
      limit(coupling, ranges.coupling);
      partNames.textContent = partsBox.disabled ? 'this model takes no body-part composition'
        : `parts (${c.skeleton}): ${model.body_parts.join(', ')}`;
      const none = pathBox.disabled && keyBox.disabled && timeBox.disabled && partsBox.disabled;
      panel.classList.toggle('disabled', none);
      const takes = [c.constraints.length ? `constraints (${c.constraints.join(', ')})` : 'no constraints',
                     c.timeline.length ? `a timeline (${c.timeline.join(', ')})` : 'no timeline'];
      why.textContent = none ? `${model.name} (${c.family}) takes no constraints and no timeline: its generation card ` +
        'lists none' : `this model takes ${takes.join(' and ')}`;
      redraw();
    },
    hasTimeline() {
      return (!timeBox.disabled && state.timeline.length > 0) || (!partsBox.disabled && state.parts.length > 0);
    },
    // Puts the panel's constraints and, with `timeline`, its timeline and body-part composition into a
    // /v1/generate body (their texts are its prompts; with segments, the last end is its length), and remembers
    // the constraints to draw them beside the result.
    apply(body, timeline) {
      state.sent = current();
      if (state.sent) body.constraints = state.sent;
      if (timeline) {
        body.timeline = timelineBody();
        body.prompts = [];
        if (!timeBox.disabled && state.timeline.length) delete body.length;
      }
      return body;
    },
    // The constraints sent beside each motion (motions[i].offset: where the viewer put it), and each motion's
    // control error in its entry of the samples list.
    showResult(result, motions, group) {
      const constrained = result.motions.some((m) => m.record.control_error_m);
      if (!constrained || !state.sent) return;
      editing.visible = false;  // the result's own markers show the same constraints, beside each motion
      motions.forEach((m, i) => {
        for (const o of constraintObjects(state.sent, result.parents, MARK)) {
          o.position.add(m.offset);
          o.userData.result = true;
          group.add(o);
        }
        const errors = result.motions[i].record.control_error_m || {};
        const unmet = result.motions[i].record.control_unmet || {};
        const text = Object.entries(errors).map(([name, e]) => `${name} ${(e * 100).toFixed(1)} cm` +
                                                 (name in unmet ? ' (not met)' : '')).join(', ');
        const entry = document.querySelectorAll('#samples .sample')[i];
        if (entry) entry.append(element('div', { className: 'control-error', textContent: `control error: ${text}` }));
      });
    },
    // read by the page's test: what the panel holds, and the constraint objects in the scene by kind (those
    // being edited, those drawn beside a result)
    debug: {
      state,
      markers() {
        const count = { editing: {}, result: {} };
        scene.traverse((o) => {
          const kind = o.userData.control;
          if (!kind) return;
          const where = count[o.userData.result ? 'result' : 'editing'];
          where[kind] = (where[kind] || 0) + 1;
        });
        return count;
      },
    },
  };
}
