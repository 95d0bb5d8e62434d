// The FastMesh page: upload -> watch -> view -> download, against the /v1 API of the server that serves it.
// Plain ES module, no build step.  The 3D viewer (three.js) is imported lazily, so a missing three.js
// install costs the 3D view only, not the form.

import { faceCount } from './facts.js';
import { flagParams, inputsHtml, valueParams } from './inputs.js';

const $ = (sel) => document.querySelector(sel);
const KEY_STORE = 'fastmesh.apiKey';
const JOBS_STORE = 'fastmesh.jobs';
const MAX_RECENT = 20;
const POLL_MS = 400;
const TIMINGS = ['queue', 'load', 'encode', 'vertices', 'enhancer', 'faces', 'filtering', 'export', 'total'];
const FINAL = ['succeeded', 'failed', 'cancelled'];
const COUNTS = ['c-vertices', 'c-faces', 'c-tokens', 'c-boundary', 'c-non-manifold', 'c-components', 'c-watertight'];

const state = {
  config: null,
  file: null,
  jobId: null,      // the job shown
  pollTimer: null,
  viewer: null,     // Viewer once three.js is loaded
  viewerPromise: null,
  viewerError: null,
  shown: {},        // what the viewer already holds for the job shown: {points, mesh}
};

// ------------------------------------------------------------------ API access

class ApiError extends Error {
  constructor(status, code, message) { super(message); this.status = status; this.code = code; }
}

function apiKey() { return localStorage.getItem(KEY_STORE) || ''; }

// Titles of the error statuses, for people; the server's own message follows.
const TITLES = {
  400: 'Bad request', 401: 'API key needed or not recognised', 404: 'Not found', 409: 'Not ready',
  413: 'File too large', 415: 'Unsupported file format', 422: 'Invalid input', 429: 'Too many requests',
  500: 'Server error', 503: 'Service unavailable',
};

async function api(path, options = {}) {
  const headers = new Headers(options.headers || {});
  const key = apiKey();
  if (key) headers.set('Authorization', `Bearer ${key}`);
  let res;
  try {
    res = await fetch(path, { ...options, headers });
  } catch (e) {
    throw new ApiError(0, 'network', `Cannot reach the server (${e.message}). Is it still running?`);
  }
  if (res.ok) return res;
  let code = `http_${res.status}`, message = res.statusText || 'request failed';
  try {
    const body = await res.json();
    if (body && body.error) ({ code, message } = body.error);
  } catch { /* not JSON: keep the status text */ }
  let title = TITLES[res.status] || `HTTP ${res.status}`;
  if (code === 'queue_full') title = 'Queue full';
  if (code === 'rate_limited') title = 'Rate limited';
  const retry = res.headers.get('Retry-After');
  const hint = retry ? ` Try again in ${retry} s.` : '';
  const end = /[.!?]$/.test(message) ? '' : '.';
  throw new ApiError(res.status, code, `${title}: ${message}${end}${hint}`);
}

function showError(message) {
  const box = $('#error');
  box.textContent = message;
  box.hidden = !message;
}

// ------------------------------------------------------------------ recent jobs (localStorage)

function recentJobs() {
  try { return JSON.parse(localStorage.getItem(JOBS_STORE) || '[]'); } catch { return []; }
}

function rememberJob(job) {
  const list = recentJobs().filter((j) => j.id !== job.id);
  const old = recentJobs().find((j) => j.id === job.id) || {};
  list.unshift({
    ...old, id: job.id, filename: job.input?.filename ?? old.filename, status: job.status,
    created_at: job.created_at ?? old.created_at, faces: job.result?.faces ?? old.faces,
  });
  localStorage.setItem(JOBS_STORE, JSON.stringify(list.slice(0, MAX_RECENT)));
  renderRecent();
}

function updateRecent(id, fields) {
  const list = recentJobs();
  const item = list.find((j) => j.id === id);
  if (!item) return;
  Object.assign(item, fields);
  localStorage.setItem(JOBS_STORE, JSON.stringify(list));
  renderRecent();
}

function forgetJob(id) {
  localStorage.setItem(JOBS_STORE, JSON.stringify(recentJobs().filter((j) => j.id !== id)));
  renderRecent();
}

function renderRecent() {
  const ul = $('#recent');
  ul.replaceChildren();
  const list = recentJobs();
  $('#recent-empty').hidden = list.length > 0;
  for (const j of list) {
    const li = document.createElement('li');
    li.dataset.id = j.id;
    if (j.id === state.jobId) li.classList.add('current');
    const a = document.createElement('a');
    a.href = `#job=${j.id}`;
    const when = j.created_at ? new Date(j.created_at).toLocaleString() : '';
    a.title = `${j.id}\n${when}`;
    a.textContent = j.filename || j.id.slice(0, 8);
    const badge = document.createElement('span');
    badge.className = `badge ${j.status || ''}`;
    badge.textContent = j.status || '?';
    const forget = document.createElement('button');
    forget.className = 'forget';
    forget.type = 'button';
    forget.title = 'Forget (this browser only)';
    forget.textContent = '×';
    forget.addEventListener('click', () => forgetJob(j.id));
    li.append(a, badge, forget);
    ul.append(li);
  }
}

// ------------------------------------------------------------------ the form

function fillDefaults() {
  const d = state.config.defaults || {};
  const bounds = state.config.bounds || {};
  const form = $('#job-form');
  const values = valueParams(state.config.params), flags = flagParams(state.config.params);
  for (const name of values) {
    const input = form.elements[name];
    if (bounds[name]) {
      input.min = bounds[name].min;
      input.max = bounds[name].max;
    }
    input.value = d[name] ?? '';
    input.placeholder = d[name] != null ? `default ${d[name]}` : 'auto (server decides)';
  }
  for (const name of flags) form.elements[name].checked = Boolean(d[name] ?? true);
  for (const box of document.querySelectorAll('#format-boxes input')) {
    box.checked = state.config.default_formats.includes(box.value);
  }
  const shown = [...values, ...flags].map((k) => `${k}=${d[k] ?? 'auto'}`).join(', ');
  $('#defaults-hint').textContent = `Server defaults: ${shown}, formats=${state.config.default_formats.join(',')}.`;
}

function buildForm() {
  // One input per generation parameter, before the formats.
  $('#job-form .formats').insertAdjacentHTML('beforebegin', inputsHtml(state.config.params));
  const boxes = $('#format-boxes');
  for (const f of state.config.formats) {
    const label = document.createElement('label');
    label.innerHTML = `<input type="checkbox" name="formats" value="${f}"> ${f.toUpperCase()}`;
    boxes.append(label);
  }
  $('#formats-hint').textContent = `${state.config.input_formats.join(', ')} · `
    + `up to ${formatBytes(state.config.max_upload_bytes)}`;
  fillDefaults();
  $('#reset-params').addEventListener('click', fillDefaults);

  const drop = $('#drop');
  $('#file').addEventListener('change', (e) => chooseFile(e.target.files[0]));
  for (const ev of ['dragenter', 'dragover']) {
    drop.addEventListener(ev, (e) => { e.preventDefault(); drop.classList.add('over'); });
  }
  for (const ev of ['dragleave', 'drop']) drop.addEventListener(ev, () => drop.classList.remove('over'));
  drop.addEventListener('drop', (e) => {
    e.preventDefault();
    if (e.dataTransfer.files.length) chooseFile(e.dataTransfer.files[0]);
  });
  $('#job-form').addEventListener('submit', (e) => { e.preventDefault(); submit(); });
}

function chooseFile(file) {
  state.file = file || null;
  showError('');
  const drop = $('#drop');
  drop.classList.toggle('chosen', Boolean(file));
  $('#drop-text').textContent = file ? `${file.name} (${formatBytes(file.size)})` : 'Drop a file here or click to choose one';
}

function formatBytes(n) {
  if (n < 1024) return `${n} B`;
  const fixed = (x) => (Number.isInteger(x) ? String(x) : x.toFixed(1));
  if (n < 1048576) return `${fixed(n / 1024)} KiB`;
  return `${fixed(n / 1048576)} MiB`;
}

async function submit() {
  showError('');
  const file = state.file;
  if (!file) { failSubmit('Choose a file first (a point cloud or a mesh).'); return; }
  const limit = state.config.max_upload_bytes;
  if (file.size > limit) {
    // Spare the upload: the server would answer 413 after receiving it all.
    failSubmit(`File too large: ${file.name} is ${formatBytes(file.size)}; this server accepts at most `
      + `${formatBytes(limit)} per upload.`);
    return;
  }
  const form = $('#job-form');
  const data = new FormData();
  data.append('file', file, file.name);
  for (const name of valueParams(state.config.params)) {
    const v = form.elements[name].value.trim();
    if (v !== '') data.append(name, v);
  }
  for (const name of flagParams(state.config.params)) {
    data.append(name, form.elements[name].checked ? 'true' : 'false');
  }
  const formats = [...document.querySelectorAll('#format-boxes input:checked')].map((b) => b.value);
  if (formats.length) data.append('formats', formats.join(','));

  const button = $('#submit');
  button.disabled = true;
  button.textContent = 'Uploading…';
  try {
    const res = await api('/v1/jobs', { method: 'POST', body: data });
    const job = await res.json();
    rememberJob(job);
    openJob(job.id, job, res.headers.get('X-Queue-Position'));
  } catch (e) {
    failSubmit(e.message);
  } finally {
    button.disabled = false;
    button.textContent = 'Generate mesh';
  }
}

// A refused submission: the error stands alone, not beside the previous job's mesh and "succeeded" badge.
function failSubmit(message) {
  closeJob('No result: the last submission was refused (see the message on the left).');
  showError(message);
}

// ------------------------------------------------------------------ watching a job

function openJob(id, job = null, position = null) {
  clearTimeout(state.pollTimer);
  if (state.jobId !== id) {
    state.jobId = id;
    state.shown = {};
    resetJobPanel();
    state.viewer?.clear();
  }
  if (location.hash !== `#job=${id}`) history.replaceState(null, '', `#job=${id}`);
  renderRecent();
  if (job) showJob(job, position);
  else poll();
}

async function poll() {
  const id = state.jobId;
  if (!id) return;
  try {
    const res = await api(`/v1/jobs/${id}`);
    if (id !== state.jobId) return;
    showJob(await res.json(), res.headers.get('X-Queue-Position'));
  } catch (e) {
    if (id !== state.jobId) return;
    if (e.status === 404) {
      updateRecent(id, { status: 'gone' });
      setStatus('gone', 'This job no longer exists (deleted, expired, or it belongs to another API key).');
    } else {
      setStatus('error', e.message);
      state.pollTimer = setTimeout(poll, POLL_MS * 5); // transient (network, 503): keep trying, slower
    }
  }
}

function setStatus(status, detail) {
  const badge = $('#status');
  badge.className = `badge ${status}`;
  badge.textContent = status;
  $('#status-detail').textContent = detail || '';
}

// Stop showing a job (deleted, or a new submission failed): empty panel and view, nothing highlighted.
function closeJob(note) {
  clearTimeout(state.pollTimer);
  state.jobId = null;
  state.shown = {};
  state.viewer?.clear();
  resetJobPanel();
  setViewerNote(note);
  $('#delete').disabled = true;
  delete $('#viewer').dataset.faces;
  delete $('#viewer').dataset.vertices;
  if (location.hash) history.replaceState(null, '', location.pathname);
  renderRecent();
}

function resetJobPanel() {
  setStatus('idle', '');
  $('#progress-bar').style.width = '0';
  for (const id of [...COUNTS, 'c-input', 'c-distance', 'c-quads', 'c-notes']) $(`#${id}`).textContent = '-';
  $('#timings tbody').replaceChildren();
  for (const id of ['dl-glb', 'dl-obj', 'dl-png']) $(`#${id}`).disabled = true;
  $('#delete').disabled = false;
  $('#cancel').hidden = true;
  setViewerNote('Waiting for the job…');
}

function setViewerNote(text) {
  const note = $('#viewer-note');
  note.textContent = text || '';
  note.hidden = !text;
}

function showJob(job, position) {
  const { status, progress } = job;
  let detail = '';
  if (status === 'queued') {
    const ahead = position == null ? null : Number(position);
    detail = ahead == null ? 'waiting for a worker' : ahead === 0 ? 'next in line' : `${ahead} job(s) ahead in the queue`;
  } else if (status === 'running') {
    detail = `${progress.stage || 'starting'} · ${Math.round((progress.fraction || 0) * 100)}%`;
  } else if (status === 'failed' || status === 'cancelled') {
    detail = job.error ? `${job.error.message} (${job.error.code})` : status;
  } else if (status === 'succeeded') {
    detail = `done in ${fmtSeconds(job.timings.total)}`;
  }
  setStatus(status, detail);
  const frac = status === 'succeeded' ? 1 : status === 'running' ? progress.fraction || 0 : 0;
  $('#progress-bar').style.width = `${Math.round(frac * 100)}%`;
  $('#cancel').hidden = FINAL.includes(status);

  const inp = job.input || {};
  state.stem = (inp.filename || '').replace(/\.[^.]*$/, '');
  $('#c-input').textContent = inp.kind === 'points' ? `${inp.points} points` : `${inp.vertices} vertices, ${inp.faces} faces`;
  if (job.result) showResultFacts(job.result);
  const tbody = $('#timings tbody');
  tbody.replaceChildren();
  for (const k of TIMINGS) {
    const v = job.timings?.[k];
    if (v == null) continue;
    const tr = document.createElement('tr');
    tr.innerHTML = `<th>${k}</th><td>${fmtSeconds(v)}</td>`;
    tbody.append(tr);
  }
  const done = status === 'succeeded';
  for (const id of ['dl-glb', 'dl-obj', 'dl-png']) $(`#${id}`).disabled = !done;
  updateRecent(job.id, { status, faces: job.result?.faces });

  loadIntoViewer(job);
  if (!FINAL.includes(status)) state.pollTimer = setTimeout(poll, POLL_MS);
}

// The counts and the quality report (result.quality) of a finished job, beside each other.
function showResultFacts(result) {
  const q = result.quality || {};
  const facts = {
    'c-vertices': result.vertices, 'c-faces': faceCount(result, state.config.face_tolerance),
    'c-tokens': result.tokens,
    'c-boundary': q.boundary_edges, 'c-non-manifold': q.non_manifold_edges, 'c-components': q.components,
    'c-watertight': q.watertight == null ? null : q.watertight ? 'yes' : 'no',
    'c-pieces': q.pieces == null ? null : `${q.pieces} / ${q.input_pieces ?? '-'}`,
    'c-closed': q.closed_decision,
    'c-from': result.result_from,
    'c-quads': q.quads == null ? null : `${q.quads} (${(100 * (q.quad_share ?? 0)).toFixed(0)} % of the polygons)`,
    'c-notes': (result.notes || []).join('; ') || null,
  };
  for (const [id, v] of Object.entries(facts)) $(`#${id}`).textContent = v ?? '-';
  $('#c-distance').textContent = q.cd == null ? '-' : `${q.cd.toFixed(2)} % / ${q.hd.toFixed(2)} %`;
}

function fmtSeconds(s) {
  if (s == null) return '-';
  return s < 1 ? `${(s * 1000).toFixed(0)} ms` : `${s.toFixed(2)} s`;
}

// ------------------------------------------------------------------ the 3D view

// One viewer per page: concurrent callers (every poll of a running job) share the same start-up promise.
function ensureViewer() {
  if (!state.viewerPromise) state.viewerPromise = startViewer();
  return state.viewerPromise;
}

async function startViewer() {
  if (!state.config.three_installed) {
    state.viewerError = 'The 3D view needs three.js, which is not installed on this server: run `make run` '
      + '(or `npm ci --prefix service/web`). Downloads work without it.';
    return null;
  }
  try {
    const { Viewer } = await import('./viewer.js');
    state.viewer = new Viewer($('#viewer'));
    $('#wireframe').addEventListener('change', (e) => state.viewer.setWireframe(e.target.checked));
    $('#points').addEventListener('change', (e) => state.viewer.setPoints(e.target.checked));
    $('#reset-view').addEventListener('click', () => state.viewer.frame());
    state.viewer.setWireframe($('#wireframe').checked);
    state.viewer.setPoints($('#points').checked);
  } catch (e) {
    state.viewerError = `The 3D view could not start: ${e.message}`;
  }
  return state.viewer;
}

const VIEW_RETRIES = 5;

async function loadIntoViewer(job) {
  const id = job.id;
  const viewer = await ensureViewer();
  if (!viewer) { setViewerNote(state.viewerError); return; }
  if (id !== state.jobId) return;
  const shown = state.shown;
  try {
    if (!shown.points) {
      shown.points = 'loading';
      const res = await api(`/v1/jobs/${id}/input.ply`);
      const buf = await res.arrayBuffer();
      if (id !== state.jobId) return;
      viewer.showPoints(buf);
      shown.points = 'done';
      if (!shown.mesh) setViewerNote('');
    }
    if (job.status === 'succeeded' && !shown.mesh) {
      shown.mesh = 'loading';
      setViewerNote('Loading the mesh…');
      const res = await api(`/v1/jobs/${id}/result?format=glb`);
      const buf = await res.arrayBuffer();
      if (id !== state.jobId) return;
      const drawn = await viewer.showMesh(buf);
      shown.mesh = 'done';
      $('#viewer').dataset.faces = String(drawn.faces);  // what the view holds (tests compare it to the API)
      $('#viewer').dataset.vertices = String(drawn.vertices);
      setViewerNote('');
    } else if (FINAL.includes(job.status) && job.status !== 'succeeded') {
      setViewerNote(`No result: job ${job.status}.`);
    }
  } catch (e) {
    if (shown.points === 'loading') shown.points = null;
    if (shown.mesh === 'loading') shown.mesh = null;
    setViewerNote(`Could not show the job in 3D: ${e.message}`);
    // A finished job is polled no more: try again a few times (a busy server answers 503 for a while).
    shown.retries = (shown.retries || 0) + 1;
    if (FINAL.includes(job.status) && shown.retries <= VIEW_RETRIES) {
      setTimeout(() => { if (state.shown === shown) loadIntoViewer(job); }, 1000 * shown.retries);
    }
  }
}

// ------------------------------------------------------------------ downloads and actions

async function download(url, fallbackName) {
  showError('');
  try {
    const res = await api(url);
    const blob = await res.blob();
    const cd = res.headers.get('Content-Disposition') || '';
    const m = /filename="([^"]+)"/.exec(cd);
    // Downloads go through fetch (they need the Authorization header), then a temporary link.
    const a = document.createElement('a');
    a.href = URL.createObjectURL(blob);
    a.download = m ? m[1] : fallbackName;
    document.body.append(a);
    a.click();
    a.remove();
    setTimeout(() => URL.revokeObjectURL(a.href), 60000);
  } catch (e) {
    showError(e.message);
  }
}

function wireActions() {
  $('#dl-glb').addEventListener('click', () => download(`/v1/jobs/${state.jobId}/result?format=glb`, 'result.glb'));
  $('#dl-obj').addEventListener('click', () => download(`/v1/jobs/${state.jobId}/result?format=obj`, 'result.obj'));
  $('#dl-png').addEventListener('click', () => download(
    `/v1/jobs/${state.jobId}/preview.png?size=1024&wireframe=${$('#wireframe').checked ? 1 : 0}`,
    `${state.stem || state.jobId}-preview.png`));
  $('#cancel').addEventListener('click', async () => {
    try { await api(`/v1/jobs/${state.jobId}`, { method: 'DELETE' }); poll(); } catch (e) { showError(e.message); }
  });
  $('#delete').addEventListener('click', async () => {
    const id = state.jobId;
    if (!id || !confirm('Delete this job and its files from the server?')) return;
    try {
      await api(`/v1/jobs/${id}`, { method: 'DELETE' });
      forgetJob(id);
      closeJob('Job deleted.');
    } catch (e) { showError(e.message); }
  });
  window.addEventListener('hashchange', openFromHash);
}

function openFromHash() {
  const m = /^#job=([0-9a-f]{32})$/.exec(location.hash);
  if (m && m[1] !== state.jobId) openJob(m[1]);
}

function setupKey() {
  if (!state.config.auth) return;
  const form = $('#key-form');
  form.hidden = false;
  const input = $('#api-key');
  input.value = apiKey();
  const say = () => { $('#key-state').textContent = apiKey() ? 'saved in this browser' : 'required'; };
  say();
  form.addEventListener('submit', (e) => {
    e.preventDefault();
    localStorage.setItem(KEY_STORE, input.value.trim());
    say();
    showError('');
    if (state.jobId) poll();
  });
}

// ------------------------------------------------------------------ start

async function main() {
  try {
    const res = await fetch('/web/config.json');
    state.config = await res.json();
  } catch (e) {
    showError(`Cannot load the page's settings from the server: ${e.message}`);
    return;
  }
  buildForm();
  setupKey();
  wireActions();
  renderRecent();
  openFromHash();
  window.fastmesh = state; // for the console (and tests): the page's state, incl. the viewer
  document.body.dataset.ready = '1'; // the page is wired (tests wait for this)
}

main();
