// pixl studio page: plain JavaScript, no libraries. Talks to the JSON API of the server that
// served it (crates/pixl-studio/README.md). The server owns all state; this page shows it, sends
// changes, and polls /api/state for background results.
"use strict";

const $ = (id) => document.getElementById(id);
let state = null;
let selected = null;        // id of the selected light
let dragging = null;        // { id, first } while a marker is dragged
let inflight = false;       // one light change at a time; later ones wait in `pending`
let pending = null;         // { id, patch }
let lastStateText = "";
const loaded = {};          // image element id -> key of what it shows

// ----- API -----------------------------------------------------------------------------------

async function api(method, path, body, raw) {
  const opts = { method, headers: {} };
  if (body !== undefined) {
    if (raw) {
      opts.body = body;
    } else {
      opts.body = JSON.stringify(body);
      opts.headers["content-type"] = "application/json";
    }
  }
  const r = await fetch(path, opts);
  const text = await r.text();
  let data = null;
  try { data = text ? JSON.parse(text) : null; } catch (_) { data = { error: text }; }
  if (!r.ok) throw new Error((data && data.error) || (r.status + " " + r.statusText));
  return data;
}

function showError(e) {
  $("error-text").textContent = String((e && e.message) || e);
  $("error").hidden = false;
}
$("error-close").onclick = () => { $("error").hidden = true; };

async function run(fn) {
  try { return await fn(); } catch (e) { showError(e); return null; }
}

// ----- colours -------------------------------------------------------------------------------

function kelvinToRgb(k) {
  // A display approximation of a blackbody's colour (swatches and markers only).
  const t = k / 100;
  let r, g, b;
  if (t <= 66) { r = 255; g = 99.47 * Math.log(t) - 161.12; b = t <= 19 ? 0 : 138.52 * Math.log(t - 10) - 305.04; }
  else { r = 329.7 * Math.pow(t - 60, -0.1332); g = 288.12 * Math.pow(t - 60, -0.0755); b = 255; }
  const c = (v) => Math.max(0, Math.min(255, Math.round(v)));
  return [c(r), c(g), c(b)];
}
const toSrgb = (v) => (v <= 0.0031308 ? 12.92 * v : 1.055 * Math.pow(v, 1 / 2.4) - 0.055);
const toLinear = (v) => (v <= 0.04045 ? v / 12.92 : Math.pow((v + 0.055) / 1.055, 2.4));

function cssColor(color) {
  if (Array.isArray(color)) {
    const m = Math.max(color[0], color[1], color[2], 1e-6);
    const s = color.map((v) => Math.round(255 * toSrgb(Math.min(1, v / Math.max(1, m)))));
    return "rgb(" + s.join(",") + ")";
  }
  return "rgb(" + kelvinToRgb(color.kelvin).join(",") + ")";
}
function hexOf(color) {
  const rgb = Array.isArray(color)
    ? color.map((v) => Math.round(255 * toSrgb(Math.max(0, Math.min(1, v)))))
    : kelvinToRgb(color.kelvin);
  return "#" + rgb.map((v) => v.toString(16).padStart(2, "0")).join("");
}
function linearOfHex(hex) {
  return [1, 3, 5].map((i) => toLinear(parseInt(hex.slice(i, i + 2), 16) / 255));
}

// ----- showing the state ---------------------------------------------------------------------

function setImage(id, name, key) {
  if (key === null || key === undefined) {
    if (loaded[id] !== null) { $(id).removeAttribute("src"); loaded[id] = null; }
    return;
  }
  if (loaded[id] === key) return;
  loaded[id] = key;
  const url = "/api/image/" + name + ".png?k=" + encodeURIComponent(key);
  const img = new Image();
  img.onload = () => { if (loaded[id] === key) { $(id).src = url; $(id).dataset.key = key; } };
  img.src = url;
}

function lightLabel(l) {
  return (l.name || l.kind + " " + l.id) + (l.enabled ? "" : " (off)");
}

function setState(s) {
  state = s;
  document.body.dataset.generation = s.generation;
  const geo = s.geometry;
  $("banner").hidden = !(geo && geo.fallback) && !(s.notes && s.notes.length);
  $("banner").textContent = [geo && geo.fallback ? geo.label : "", ...(s.notes || [])].filter(Boolean).join(" ");
  $("drop-hint").hidden = !!s.photo;
  $("export-video").hidden = !s.video;
  $("undo").disabled = !s.can_undo;
  $("redo").disabled = !s.can_redo;

  // Images: the photo at once; over it the newest relit image (kept up while the next one
  // renders), the quick preview until there is one, and nothing while no light is placed.
  const photoKey = s.photo ? s.photo.name + "|" + (geo ? geo.label : "") + "|" + s.photo.work.join("x") : null;
  setImage("before", "photo", photoKey);
  const r = s.rendered;
  const current = r && r.generation === s.generation;
  const pv = s.preview ? "p" + s.preview.generation : null;
  const rk = r ? "r" + r.generation + "." + r.stage : null;
  if (r && s.lights.length) {
    setImage("after", "relit", rk);
    $("after").dataset.kind = current ? (r.final ? "relit-final" : "relit") : "relit-previous";
  } else if (s.lights.length) {
    setImage("after", "preview", pv);
    $("after").dataset.kind = pv ? "preview" : "";
  } else {
    setImage("after", "preview", null);
    $("after").dataset.kind = "";
  }
  setImage("p-preview", "preview", pv);
  const like = s.like;
  $("like-panel").hidden = !like;
  setImage("p-like", "like", like ? "l" + like.id : null);
  if (like) {
    $("like-caption").textContent = "relit like " + like.reference +
      (like.aspect_differs ? " (another frame shape: stretched)" : "");
  }
  $("like-button").classList.toggle("disabled", !s.can_like || !s.photo);
  $("like-button").title = s.can_like
    ? "Relight the photo with the lighting of another photo of the same view (its intrinsics from Marigold-IID-Lighting)"
    : "Needs Marigold-IID-Lighting's weights on disk (pixl models fetch marigold-lighting)";
  for (const n of ["render", "albedo", "shading", "residual", "relit"]) setImage("p-" + n, n, rk);

  // Status line.
  let status = "";
  if (!s.photo) status = "no photo yet";
  else if (!s.lights.length && !s.busy) status = "no lights: click the photo to add one, or pick a preset";
  else if (s.busy) status = s.busy + " …";
  else if (current) status = "done: relit with " + r.spp + " spp render" + (r.final ? "" : " (more samples coming)");
  else if (r) status = "showing the last relit image; the new lights render when they stop changing";
  else status = "preview (the render starts when the lights stop changing)";
  if (s.error) status += " — " + s.error;
  $("status").textContent = status;
  $("info").textContent = s.photo
    ? s.photo.name + " (" + s.photo.width + "×" + s.photo.height + ", working size " + s.photo.work.join("×") + "); " +
      (geo ? geo.label : "") + "; weights: " + s.weights + "; saves to " + s.out_dir
    : "weights: " + s.weights;

  renderLights();
}

function renderLights() {
  const s = state;
  if (!s) return;
  if (selected !== null && !s.lights.some((l) => l.id === selected)) selected = null;
  const list = $("light-list");
  list.textContent = "";
  for (const l of s.lights) {
    const li = document.createElement("li");
    li.dataset.id = l.id;
    if (l.id === selected) li.className = "selected";
    const sw = document.createElement("span");
    sw.className = "swatch";
    sw.style.background = cssColor(l.color);
    li.append(sw, document.createTextNode(lightLabel(l)));
    li.onclick = () => { selected = l.id; renderLights(); };
    list.append(li);
  }
  // Markers are kept (moved, restyled) rather than rebuilt, so a drag or a click in progress
  // never loses its element.
  const layer = $("markers");
  const want = new Set(s.lights.filter((l) => l.uv).map((l) => String(l.id)));
  for (const m of [...layer.querySelectorAll(".marker")]) {
    if (!want.has(m.dataset.id) && !(dragging && Number(m.dataset.id) === dragging.id)) m.remove();
  }
  for (const l of s.lights) {
    if (!l.uv) continue;
    let m = layer.querySelector('.marker[data-id="' + l.id + '"]');
    if (!m) {
      m = document.createElement("div");
      m.dataset.id = l.id;
      m.addEventListener("pointerdown", startDrag);
      layer.append(m);
    }
    m.className = "marker kind-" + l.kind + (l.id === selected ? " selected" : "") + (l.enabled ? "" : " disabled");
    m.title = lightLabel(l);
    m.style.background = cssColor(l.color);
    if (!(dragging && dragging.id === l.id)) {
      m.style.left = (100 * l.uv[0]) + "%";
      m.style.top = (100 * l.uv[1]) + "%";
    }
  }
  renderEditor();
}

function setRange(id, value, text) {
  const el = $(id);
  if (document.activeElement !== el) el.value = value;
  const out = $("o-" + id.slice(2));
  if (out) out.textContent = text;
}

function renderEditor() {
  const l = state && state.lights.find((x) => x.id === selected);
  $("editor").hidden = !l;
  if (!l) return;
  const radius = (state.geometry && state.geometry.radius) || 1;
  $("editor-title").textContent = lightLabel(l);
  $("e-kind").value = l.kind;
  $("e-enabled").checked = l.enabled;
  const kelvin = !Array.isArray(l.color);
  if (document.activeElement !== $("e-colormode")) $("e-colormode").value = kelvin ? "kelvin" : "rgb";
  $("row-kelvin").hidden = !kelvin;
  $("row-rgb").hidden = kelvin;
  if (kelvin) setRange("e-kelvin", l.color.kelvin, Math.round(l.color.kelvin));
  else if (document.activeElement !== $("e-rgb")) $("e-rgb").value = hexOf(l.color);
  setRange("e-power", Math.log10(Math.max(l.power, 1e-3)), l.power.toPrecision(3) +
    (l.kind === "sun" ? " W/m²" : l.kind === "environment" ? " ×" : " W"));
  const placed = l.kind !== "environment";
  $("row-distance").hidden = !placed || l.kind === "sun";
  $("e-distance").max = Math.max(2 * radius, l.distance * 1.5).toFixed(3);
  setRange("e-distance", l.distance, l.distance.toFixed(2));
  $("row-size").hidden = !placed;
  const sizeMax = l.kind === "sun" ? 30 : l.kind === "area" ? 2 * radius : 0.5 * radius;
  $("e-size").max = Math.max(sizeMax, l.size).toFixed(3);
  setRange("e-size", l.size, l.size.toFixed(2) + (l.kind === "sun" ? "°" : " m"));
  $("row-spot").hidden = l.kind !== "spot";
  $("row-blend").hidden = l.kind !== "spot";
  setRange("e-spot", l.spot_deg, Math.round(l.spot_deg));
  setRange("e-blend", l.blend, l.blend.toFixed(2));
}

// ----- changing lights -----------------------------------------------------------------------

async function flush() {
  if (inflight || !pending) return;
  const { id, patch } = pending;
  pending = null;
  inflight = true;
  try {
    const res = await api("PUT", "/api/lights/" + id, patch);
    setState(res.state);
  } catch (e) {
    showError(e);
  } finally {
    inflight = false;
    if (pending) flush();
  }
}

function change(id, patch) {
  if (pending && pending.id === id) {
    // Merge: the newest value of each field wins; coalesce only if every merged change did.
    pending.patch = Object.assign({}, pending.patch, patch, { coalesce: pending.patch.coalesce && patch.coalesce });
  } else {
    if (pending) flush();
    pending = { id, patch };
  }
  flush();
}

function uvOf(ev) {
  const r = $("markers").getBoundingClientRect();
  const u = Math.min(1, Math.max(0, (ev.clientX - r.left) / r.width));
  const v = Math.min(1, Math.max(0, (ev.clientY - r.top) / r.height));
  return [u, v];
}

$("markers").addEventListener("click", (ev) => {
  if (ev.target !== $("markers") || !state || !state.photo) return;
  const kind = $("new-kind").value;
  run(async () => {
    const res = await api("POST", "/api/lights", { kind, anchor: uvOf(ev) });
    selected = res.light.id;
    setState(res.state);
  });
});

function startDrag(ev) {
  ev.preventDefault();
  ev.stopPropagation();
  const id = Number(ev.currentTarget.dataset.id);
  selected = id;
  dragging = { id, first: true, el: ev.currentTarget };
  ev.currentTarget.setPointerCapture(ev.pointerId);
  ev.currentTarget.addEventListener("pointermove", moveDrag);
  ev.currentTarget.addEventListener("pointerup", endDrag);
  ev.currentTarget.addEventListener("pointercancel", endDrag);
  renderEditor();
}

function moveDrag(ev) {
  if (!dragging) return;
  const uv = uvOf(ev);
  dragging.el.style.left = (100 * uv[0]) + "%";
  dragging.el.style.top = (100 * uv[1]) + "%";
  change(dragging.id, { anchor: uv, coalesce: !dragging.first });
  dragging.first = false;
}

function endDrag(ev) {
  if (!dragging) return;
  const el = dragging.el;
  el.removeEventListener("pointermove", moveDrag);
  el.removeEventListener("pointerup", endDrag);
  el.removeEventListener("pointercancel", endDrag);
  if (!dragging.first) change(dragging.id, { anchor: uvOf(ev), coalesce: true });
  dragging = null;
  renderLights();
}

function bindEditor(id, event, patchOf) {
  $(id).addEventListener(event, () => {
    if (selected === null) return;
    change(selected, Object.assign(patchOf($(id).value, $(id)), { coalesce: event === "input" }));
  });
}
bindEditor("e-kind", "change", (v) => ({ kind: v }));
$("e-enabled").addEventListener("change", () => {
  if (selected !== null) change(selected, { enabled: $("e-enabled").checked, coalesce: false });
});
$("e-colormode").addEventListener("change", () => {
  if (selected === null) return;
  const l = state.lights.find((x) => x.id === selected);
  if (!l) return;
  if ($("e-colormode").value === "kelvin") change(selected, { color: { kelvin: 5000 }, coalesce: false });
  else change(selected, { color: linearOfHex(hexOf(l.color)), coalesce: false });
});
bindEditor("e-kelvin", "input", (v) => ({ color: { kelvin: Number(v) } }));
bindEditor("e-rgb", "input", (v) => ({ color: linearOfHex(v) }));
bindEditor("e-power", "input", (v) => ({ power: Math.pow(10, Number(v)) }));
bindEditor("e-distance", "input", (v) => ({ distance: Number(v) }));
bindEditor("e-size", "input", (v) => ({ size: Number(v) }));
bindEditor("e-spot", "input", (v) => ({ spot_deg: Number(v) }));
bindEditor("e-blend", "input", (v) => ({ blend: Number(v) }));

async function deleteSelected() {
  if (selected === null) return;
  const id = selected;
  selected = null;
  await run(async () => setState(await api("DELETE", "/api/lights/" + id)));
}
$("e-delete").onclick = deleteSelected;

async function history(which) {
  await run(async () => setState((await api("POST", "/api/" + which)).state));
}
$("undo").onclick = () => history("undo");
$("redo").onclick = () => history("redo");
document.addEventListener("keydown", (ev) => {
  if (ev.target && (ev.target.tagName === "INPUT" || ev.target.tagName === "SELECT")) return;
  const mod = ev.ctrlKey || ev.metaKey;
  if (mod && ev.key.toLowerCase() === "z") { ev.preventDefault(); history(ev.shiftKey ? "redo" : "undo"); }
  else if (mod && ev.key.toLowerCase() === "y") { ev.preventDefault(); history("redo"); }
  else if (ev.key === "Delete" || ev.key === "Backspace") deleteSelected();
});

// ----- files ---------------------------------------------------------------------------------

async function upload(path, file) {
  $("status").textContent = "loading " + file.name + " …";
  await run(async () => {
    const s = await api("POST", path + (path.includes("?") ? "&" : "?") + "name=" + encodeURIComponent(file.name), file, true);
    selected = null;
    setState(s);
  });
}
function ext(name) { const i = name.lastIndexOf("."); return i < 0 ? "" : name.slice(i + 1).toLowerCase(); }
function openFile(file) {
  const e = ext(file.name);
  if (e === "exr" || e === "npy") return upload("/api/depth?kind=" + $("depth-kind").value, file);
  if (e === "toml" || e === "json") return upload("/api/scene?format=" + e, file);
  return upload("/api/photo", file);
}
$("photo-file").onchange = (ev) => { if (ev.target.files[0]) upload("/api/photo", ev.target.files[0]); ev.target.value = ""; };
$("like-file").onchange = (ev) => {
  const f = ev.target.files[0];
  ev.target.value = "";
  if (!f) return;
  $("status").textContent = "reading the lighting of " + f.name + " …";
  run(async () => {
    const res = await api("POST", "/api/like?name=" + encodeURIComponent(f.name), f, true);
    setState(res.state);
    $("status").textContent = "relit like " + f.name + " (panel on the right)";
  });
};
$("depth-file").onchange = (ev) => {
  if (ev.target.files[0]) upload("/api/depth?kind=" + $("depth-kind").value, ev.target.files[0]);
  ev.target.value = "";
};
$("scene-file").onchange = (ev) => {
  const f = ev.target.files[0];
  if (f) upload("/api/scene?format=" + (ext(f.name) === "json" ? "json" : "toml"), f);
  ev.target.value = "";
};
const stage = $("stage");
stage.addEventListener("dragover", (ev) => { ev.preventDefault(); stage.classList.add("dragover"); });
stage.addEventListener("dragleave", () => stage.classList.remove("dragover"));
stage.addEventListener("drop", (ev) => {
  ev.preventDefault();
  stage.classList.remove("dragover");
  const f = ev.dataTransfer && ev.dataTransfer.files[0];
  if (f) openFile(f);
});

$("save").onclick = () => run(async () => {
  const res = await api("POST", "/api/save");
  $("status").textContent = "saved " + res.path;
  $("status").dataset.saved = res.path;
});
for (const [id, what] of [["export-relit", "relit"], ["export-ct", "ct"], ["export-blender", "blender"], ["export-video", "video"]]) {
  $(id).onclick = () => run(async () => {
    $("status").textContent = "exporting " + what + " (waiting for the final render) …";
    const res = await api("POST", "/api/export?what=" + what);
    $("status").textContent = "wrote " + res.paths.join(", ");
  });
}

// ----- presets, before/after, polling ----------------------------------------------------------

function buildPresets(names) {
  const box = $("presets");
  if (box.childElementCount) return;
  for (const n of names) {
    const b = document.createElement("button");
    b.id = "preset-" + n;
    b.textContent = n;
    b.onclick = () => run(async () => { selected = null; setState(await api("POST", "/api/preset", { name: n })); });
    box.append(b);
  }
}

function setBeforeAfter() {
  const v = Number($("before-after").value);
  $("after-clip").style.clipPath = "inset(0 " + (100 - v) + "% 0 0)";
}
$("before-after").addEventListener("input", setBeforeAfter);
setBeforeAfter();

async function poll() {
  if (!inflight && !dragging) {
    try {
      const r = await fetch("/api/state");
      const text = await r.text();
      if (text !== lastStateText) {
        lastStateText = text;
        const s = JSON.parse(text);
        buildPresets(s.presets);
        setState(s);
      }
    } catch (e) {
      $("status").textContent = "cannot reach the server (" + e.message + ")";
    }
  }
  setTimeout(poll, state && state.busy ? 200 : 500);
}
poll();
