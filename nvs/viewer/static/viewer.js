"use strict";
// The viewer page. One view request is in flight at a time; while it runs only the latest pose waits, so a drag
// never queues stale views. body[data-views] counts finished views and body[data-busy] says whether one is running.

const $ = (id) => document.getElementById(id);
const state = { info: null, axes: [], source: null, values: {}, busy: false, pending: false, views: 0, recent: [] };

function showError(message) {
  $("error").textContent = message;
  $("error").hidden = false;
}

function clearError() {
  $("error").textContent = "";
  $("error").hidden = true;
}

async function fetchJSON(url, options) {
  let response;
  try {
    response = await fetch(url, options);
  } catch (err) {
    throw new Error(`the viewer server is not reachable (${err.message})`);
  }
  let body;
  try {
    body = await response.json();
  } catch {
    throw new Error(`the server answered ${response.status} ${response.statusText}`);
  }
  if (!response.ok) throw new Error(body.error || `the server answered ${response.status}`);
  return body;
}

function show(value, ax) {
  return ax.unit === "°" ? `${Math.round(value)}°` : `${value.toFixed(2)} ${ax.unit}`;
}

function snap(value, ax) {
  const v = Math.round(value / ax.step) * ax.step;
  return Math.min(ax.max, Math.max(ax.min, +v.toFixed(6)));
}

function setValues(values) {
  for (const ax of state.axes) {
    state.values[ax.name] = snap(values[ax.name], ax);
    $(`axis-${ax.name}`).value = state.values[ax.name];
    $(`value-${ax.name}`).textContent = show(state.values[ax.name], ax);
  }
}

function buildControls(axes) {
  const box = $("controls");
  for (const ax of axes) {
    const label = document.createElement("label");
    label.htmlFor = `axis-${ax.name}`;
    label.textContent = ax.label;
    const input = document.createElement("input");
    Object.assign(input, { type: "range", id: `axis-${ax.name}`, min: ax.min, max: ax.max, step: ax.step });
    input.addEventListener("input", () => {
      setValues({ ...state.values, [ax.name]: +input.value });
      requestView();
    });
    const out = document.createElement("span");
    const value = document.createElement("output");
    value.id = `value-${ax.name}`;
    out.append(value, ` (trained range ${show(ax.min, ax)} … ${show(ax.max, ax)})`);
    box.append(label, input, out);
  }
}

function addToGallery(source) {
  const button = document.createElement("button");
  button.type = "button";
  button.title = source.label;
  button.dataset.key = source.key;
  const img = document.createElement("img");
  img.src = source.image;
  img.alt = source.label;
  button.append(img);
  button.addEventListener("click", () => selectSource(source));
  $("gallery").append(button);
}

function selectSource(source) {
  state.source = source;
  $("source").src = source.image;
  $("source-label").textContent = source.label;
  for (const b of $("gallery").children) b.classList.toggle("selected", b.dataset.key === source.key);
  setValues(source.initial);
  requestView();
}

function record(ms, view) {
  state.views += 1;
  document.body.dataset.views = String(state.views);
  state.recent = [...state.recent.slice(-19), ms];
  const sorted = [...state.recent].sort((a, b) => a - b);
  const median = sorted[Math.floor(sorted.length / 2)];
  const encoder = view.encoded ? ", encoder ran: new source" : "";
  $("route-taken").textContent = view.route ? `this view: ${view.route}${routeFeatures(view.route_features)}` : "";
  document.body.dataset.route = view.route || "";
  $("stats").textContent = `latency per view: ${ms.toFixed(0)} ms end to end (model ${view.model_ms.toFixed(0)} ms, `
    + `server ${view.server_ms.toFixed(0)} ms${encoder}) · median of the last ${sorted.length}: `
    + `${median.toFixed(0)} ms ≈ ${(1000 / median).toFixed(1)} views/s`;
}

function routeFeatures(f) {
  // what the rule read; null: not computed for this view (a copied view runs no network)
  const parts = [["pose bound", f.pose_px, " px"], ["mean displacement", f.disp_mean_px, " px"],
    ["disocclusion", f.disocclusion === null ? null : 100 * f.disocclusion, "%"]]
    .filter(([, v]) => v !== null).map(([name, v, unit]) => `${name} ${v.toFixed(1)}${unit}`);
  return parts.length ? ` (${parts.join(", ")})` : "";
}

function requestView() {
  if (!state.source) return;
  if (state.busy) {
    state.pending = true;
    return;
  }
  state.busy = true;
  document.body.dataset.busy = "true";
  const params = poseParams();
  const t0 = performance.now();
  fetchJSON(`/api/view?${params}`)
    .then(async (view) => {
      $("synth").src = view.rgb;
      if (view.depth) {
        $("depth").src = view.depth;
        const [near, far] = view.depth_range;
        $("depth-caption").textContent = `predicted depth (near = bright; ${near.toFixed(2)} … ${far.toFixed(2)})`;
      } else {
        $("depth").removeAttribute("src");
        $("depth-caption").textContent = "this model predicts no depth";
      }
      await Promise.all([$("synth").decode(), view.depth ? $("depth").decode() : null]).catch(() => {});
      record(performance.now() - t0, view);
      clearError();
    })
    .catch((err) => showError(err.message))
    .finally(() => {
      state.busy = false;
      if (state.pending) {
        state.pending = false;
        requestView();
      } else {
        document.body.dataset.busy = "false";
      }
    });
}

function setUpDrag() {
  // Dragging across the whole panel sweeps an axis over its full range: horizontal -> axes[0], up -> axes[1].
  const panel = $("drag");
  let start = null;
  panel.addEventListener("pointerdown", (e) => {
    start = { x: e.clientX, y: e.clientY, values: { ...state.values } };
    panel.setPointerCapture(e.pointerId);
    panel.classList.add("dragging");
    e.preventDefault();
  });
  panel.addEventListener("pointermove", (e) => {
    if (!start) return;
    const [h, v] = state.axes;
    const width = panel.clientWidth || 256;
    setValues({
      [h.name]: start.values[h.name] + ((e.clientX - start.x) / width) * (h.max - h.min),
      [v.name]: start.values[v.name] + ((start.y - e.clientY) / width) * (v.max - v.min),
    });
    requestView();
  });
  const end = () => {
    start = null;
    panel.classList.remove("dragging");
  };
  panel.addEventListener("pointerup", end);
  panel.addEventListener("pointercancel", end);
}

function setUpUpload() {
  $("upload").addEventListener("change", async (e) => {
    const file = e.target.files[0];
    if (!file) return;
    const form = new FormData();
    form.append("image", file, file.name);
    $("upload-note").textContent = "uploading…";
    try {
      const source = await fetchJSON("/api/upload", { method: "POST", body: form });
      if (!$("gallery").querySelector(`[data-key="${source.key}"]`)) addToGallery(source);
      $("upload-note").textContent = state.info.controls.kind === "object"
        ? "An uploaded image is taken as seen from azimuth 0°, elevation 0°." : "";
      selectSource(source);
    } catch (err) {
      $("upload-note").textContent = "";
      showError(`Upload failed: ${err.message}`);
    } finally {
      e.target.value = "";
    }
  });
}

function poseParams() {
  const params = new URLSearchParams({ source: state.source.key });
  for (const [name, value] of Object.entries(state.values)) params.set(name, String(value));
  if ($("route").checked) params.set("route", "1");
  return params;
}

function setUpExport(paths) {
  // The point cloud is a plain download of /api/ply at the current pose; a video is rendered on the server (the
  // views one at a time, like every other request) and shown here as a GIF with download links.
  $("ply-button").addEventListener("click", () => {
    if (!state.source) return;
    const link = document.createElement("a");
    link.href = `/api/ply?${poseParams()}`;
    link.download = "";
    document.body.append(link);
    link.click();
    link.remove();
  });
  for (const path of paths) $("video-path").append(new Option(path, path));
  $("video-button").addEventListener("click", async () => {
    if (!state.source) return;
    const params = new URLSearchParams({ source: state.source.key, path: $("video-path").value,
                                         frames: $("video-frames").value, fps: $("video-fps").value });
    $("video-button").disabled = true;
    document.body.dataset.video = "rendering";
    $("video-note").textContent = `rendering ${params.get("frames")} frames…`;
    try {
      const clip = await fetchJSON(`/api/video?${params}`);
      $("video").src = clip.gif;
      $("video-gif").href = clip.gif;
      $("video-mp4").href = clip.mp4;
      const stem = `${params.get("path")}_${state.source.label}`.replace(/[^A-Za-z0-9_.-]+/g, "_");
      $("video-gif").download = `${stem}.gif`;
      $("video-mp4").download = `${stem}.mp4`;
      $("video-figure").hidden = false;
      $("video-note").textContent = `${clip.frames} frames in ${(clip.ms / 1000).toFixed(1)} s`;
      clearError();
    } catch (err) {
      $("video-note").textContent = "";
      showError(`Video failed: ${err.message}`);
    } finally {
      $("video-button").disabled = false;
      document.body.dataset.video = "done";
    }
  });
}

async function init() {
  try {
    const info = await fetchJSON("/api/info");
    state.info = info;
    state.axes = info.controls.axes;
    const split = info.encoder_once ? "encoder once per source, pose step per view" : "whole network per view";
    $("model").textContent = `model ${info.model} · data ${info.data} · ${info.image_size}² · ${info.precision}`
      + ` · ${split} · ${info.checkpoint}`;
    buildControls(state.axes);
    if (info.route) {  // the viewer was started with route=<rule file>
      $("route-box").hidden = false;
      $("route").addEventListener("change", requestView);
    }
    for (const source of info.gallery) addToGallery(source);
    setUpDrag();
    setUpUpload();
    setUpExport(info.paths);
    selectSource(info.gallery[0]);
  } catch (err) {
    showError(err.message);
  }
}

init();
