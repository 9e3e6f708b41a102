// monoloc operator's console: one page, hash routes, plain DOM + Plotly. The API key is
// kept in sessionStorage and sent as X-API-Key; what the key may do is learnt at sign-in
// by asking the routes themselves (200 or 403), so the page never guesses a scope.
"use strict";

const KEY_STORE = "monoloc.apiKey";
const TAG_COLOURS = {
  day: "#1f77b4", night: "#6a3d9a", "off-center": "#ff7f0e",
  "night+off-center": "#d62728",
};
const PALETTE = ["#2ca02c", "#8c564b", "#e377c2", "#17becf", "#bcbd22", "#7f7f7f"];
const VEHICLE_COLOURS = ["#d62728", "#2ca02c", "#ff7f0e", "#9467bd", "#17becf"];
const state = { key: null, caps: null, timers: [], aborts: [] };
const $ = (sel, root = document) => root.querySelector(sel);
const view = () => $("#view");

class ApiError extends Error {
  constructor(status, message) { super(message); this.status = status; }
}

async function api(path, options = {}) {
  const headers = Object.assign({ "X-API-Key": state.key }, options.headers || {});
  const response = await fetch(path, Object.assign({}, options, { headers }));
  if (!response.ok) {
    let message = response.statusText;
    try { message = (await response.json()).error.message; } catch (e) { /* not JSON */ }
    throw new ApiError(response.status, message);
  }
  return response.status === 204 ? null : response.json();
}

function h(tag, attrs = {}, ...children) {
  const el = document.createElement(tag);
  for (const [k, v] of Object.entries(attrs)) {
    if (k.startsWith("on")) el.addEventListener(k.slice(2), v);
    else if (v !== null && v !== undefined && v !== false) el.setAttribute(k, v === true ? "" : v);
  }
  for (const c of children.flat()) el.append(c instanceof Node ? c : String(c ?? ""));
  return el;
}

function show(...nodes) { view().replaceChildren(...nodes); }
function setStatus(text) { $("#status").textContent = text; }
function fmt(x, digits = 2) { return x === null || x === undefined ? "-" : Number(x).toFixed(digits); }
function deg(rad) { return rad === null || rad === undefined ? "-" : (rad * 180 / Math.PI).toFixed(1) + "°"; }

// ---- sign-in and what the key may do ------------------------------------------------

// Every valid key reads the maps (and live vehicles); map:write also edits, admin all.
async function capabilities() {
  const me = await api("/v1/keys/me");
  const admin = me.scopes.includes("admin");
  return { read: true, write: admin || me.scopes.includes("map:write"), admin, scopes: me.scopes };
}

function scopeLabel(caps) {
  if (caps.admin) return "admin";
  return ["localize", "map:write"].filter((s) => caps.scopes.includes(s)).join(" + ");
}

async function signIn(key) {
  state.key = key;
  const caps = await capabilities();
  state.caps = caps;
  sessionStorage.setItem(KEY_STORE, key);
  $("#who").textContent = `key ${key.slice(0, 8)}… · ${scopeLabel(caps)}`;
  $("#who").dataset.scope = scopeLabel(caps);
  $("#nav").hidden = false;
  $("#signout").hidden = false;
  for (const a of document.querySelectorAll("#nav [data-needs]")) {
    a.hidden = !caps[a.dataset.needs];
  }
}

function signOut() {
  sessionStorage.removeItem(KEY_STORE);
  state.key = state.caps = null;
  $("#nav").hidden = $("#signout").hidden = true;
  $("#who").textContent = "";
  location.hash = "#/signin";
  route();
}

function signInPage(message) {
  const input = h("input", { id: "key", type: "password", placeholder: "mlk_…", autocomplete: "off" });
  const error = h("p", { id: "signin-error", class: "error" }, message || "");
  const submit = async (event) => {
    event.preventDefault();
    error.textContent = "";
    try {
      await signIn(input.value.trim());
      const target = "#/maps";
      if (location.hash === target) await route(); else location.hash = target;
    } catch (e) {
      state.key = null;
      error.textContent = e.status === 401 ? `sign-in refused: ${e.message}` : e.message;
    }
  };
  show(h("form", { class: "signin card", onsubmit: submit },
    h("h1", {}, "Sign in"),
    h("p", { class: "muted" }, "Paste an API key. It stays in this tab (session storage)."),
    input, h("p", {}, h("button", { id: "signin", class: "primary", type: "submit" }, "Sign in")),
    error));
  input.focus();
}

// ---- maps -----------------------------------------------------------------------------

async function mapsPage() {
  const maps = (await api("/v1/maps")).items;
  const rows = maps.map((m) => h("tr", { "data-map-id": m.id },
    h("td", {}, h("a", { href: `#/maps/${m.id}` }, m.name)), h("td", {}, m.id),
    h("td", { class: "n-entries" }, m.n_entries), h("td", {}, m.version),
    h("td", {}, `${m.vocabulary.hash.slice(0, 10)} (${m.vocabulary.n_words} words)`),
    h("td", {}, calibration(m)),
    h("td", {}, h("a", { href: `#/maps/${m.id}/live` }, "live"))));
  show(h("h1", {}, "Maps"),
    h("table", { id: "maps" },
      h("thead", {}, h("tr", {}, ["name", "id", "entries", "version", "vocabulary",
        "measurement model", ""].map((t) => h("th", {}, t)))),
      h("tbody", {}, rows.length ? rows : h("tr", {}, h("td", { colspan: 7 }, "no map yet")))));
}

// "calibrated", with the conditions that have a model of their own ("+night")
function calibration(m) {
  if (!m.calibrated) return "defaults";
  const conditions = m.calibrated_conditions || [];
  return conditions.length ? `calibrated (+${conditions.join(", +")})` : "calibrated";
}

function category(tags) {
  return tags.length ? [...tags].sort().join("+") : "day";
}

function colourOf(name, index) {
  return TAG_COLOURS[name] || PALETTE[index % PALETTE.length];
}

// Entry poses as one arrow trace per tag combination (arrow angle: clockwise from up).
function entryTraces(poses, keep, options = {}) {
  const groups = new Map();
  poses.entry_ids.forEach((id, i) => {
    if (!keep(i)) return;
    const name = category(poses.tags[i]);
    if (!groups.has(name)) groups.set(name, []);
    groups.get(name).push(i);
  });
  const names = [...groups.keys()].sort();
  return names.map((name, k) => {
    const idx = groups.get(name);
    return {
      type: "scatter", mode: "markers", name: `${name} (${idx.length})`,
      meta: { tag: name },
      x: idx.map((i) => poses.x_m[i]), y: idx.map((i) => poses.y_m[i]),
      customdata: idx.map((i) => poses.entry_ids[i]),
      text: idx.map((i) => `entry ${poses.entry_ids[i]} · run ${poses.run_ids[i] ?? "-"} · ` +
        `${deg(poses.yaw_rad[i])} · ${poses.tags[i].join(", ") || "no tag"}`),
      hoverinfo: "text",
      marker: {
        symbol: "arrow", size: options.size || 11,
        angle: idx.map((i) => 90 - poses.yaw_rad[i] * 180 / Math.PI),
        color: options.colour || colourOf(name, k), opacity: options.opacity || 0.9,
        line: { width: 0 },
      },
    };
  });
}

function gapTrace(coverage) {
  const x = [], y = [];
  for (const g of coverage.gaps) { x.push(...g.x_m, null); y.push(...g.y_m, null); }
  return {
    type: "scatter", mode: "lines", name: `coverage gaps (${coverage.gaps.length}, ` +
      `${fmt(coverage.gap_length_m, 0)} m)`, meta: { gaps: coverage.gaps.length },
    x, y, hoverinfo: "name", line: { color: "#e53935", width: 6 }, opacity: 0.45,
  };
}

function plotLayout(extra = {}) {
  return Object.assign({
    margin: { l: 55, r: 10, t: 10, b: 45 }, dragmode: "pan", hovermode: "closest",
    xaxis: { title: { text: "x (m)" }, zeroline: false },
    yaxis: { title: { text: "y (m)" }, scaleanchor: "x", zeroline: false },
    legend: { orientation: "h", y: -0.12 }, uirevision: "keep",
  }, extra);
}
const PLOT_CONFIG = { scrollZoom: true, responsive: true, displaylogo: false };

async function mapPage(mapId) {
  const detail = await api(`/v1/maps/${mapId}`);
  const poses = await api(`/v1/maps/${mapId}/poses`);
  const tags = [...new Set(poses.tags.map(category))].sort();
  const runs = [...new Set(poses.run_ids.filter((r) => r !== null))].sort((a, b) => a - b);
  const tagSel = h("select", { id: "filter-tag" }, h("option", { value: "" }, "all"),
    tags.map((t) => h("option", { value: t }, t)));
  const runSel = h("select", { id: "filter-run" }, h("option", { value: "" }, "all"),
    runs.map((r) => h("option", { value: r }, `run ${r}`)));
  const radius = h("input", { id: "gap-radius", type: "number", min: 0.5, step: 0.5, value: 5 });
  const plot = h("div", { id: "map-plot", class: "plot" });
  const info = h("p", { id: "plot-info", class: "muted" });
  const links = [h("a", { href: `#/maps/${mapId}/live` }, "live vehicles")];
  if (state.caps.write) links.push(" · ", h("a", { id: "add-link", href: `#/maps/${mapId}/add` }, "add images"));
  show(h("h1", {}, `Map ${detail.name}`),
    h("p", { class: "muted" }, `${detail.n_entries} entries · ${detail.n_runs} runs · ` +
      `version ${detail.version} · vocabulary ${detail.vocabulary.hash.slice(0, 10)} · ` +
      (detail.calibrated ? calibration(detail) : "measurement model: defaults")),
    h("p", {}, links),
    h("div", { class: "toolbar" }, h("label", {}, "tag", tagSel), h("label", {}, "run", runSel),
      h("label", {}, "gap radius (m)", radius)),
    plot, info);

  async function draw() {
    const tag = tagSel.value, run = runSel.value;
    const keep = (i) => (!tag || category(poses.tags[i]) === tag) &&
      (!run || String(poses.run_ids[i]) === run);
    const params = new URLSearchParams({ radius_m: radius.value || "5" });
    // the coverage filter is by one tag; "day" (untagged) has no server-side tag
    if (tag && tag !== "day" && !tag.includes("+")) params.set("tag", tag);
    if (run) params.set("run_id", run);
    const coverage = await api(`/v1/maps/${mapId}/coverage?${params}`);
    const traces = [gapTrace(coverage), ...entryTraces(poses, keep)];
    await Plotly.react(plot, traces, plotLayout(), PLOT_CONFIG);
    const shown = traces.slice(1).reduce((n, t) => n + t.x.length, 0);
    plot.dataset.entries = shown;
    info.textContent = `${shown} entries shown · route ${fmt(coverage.route_length_m, 0)} m · ` +
      `${coverage.gaps.length} gaps (${fmt(coverage.gap_length_m, 0)} m) with no shown entry within ` +
      `${coverage.radius_m} m` + (state.caps.write ? " · click an entry to open it" : "");
  }
  for (const el of [tagSel, runSel, radius]) el.addEventListener("change", () => draw().catch(fail));
  await draw();
  if (state.caps.write) {
    plot.on("plotly_click", (event) => {
      const id = event.points[0] && event.points[0].customdata;
      if (id !== undefined) location.hash = `#/maps/${mapId}/entries/${id}`;
    });
  }
}

// ---- one entry ------------------------------------------------------------------------

// The entry's image (fetched with the key, as a data URI for Plotly's image trace), or null.
async function entryImage(mapId, entryId) {
  const response = await fetch(`/v1/maps/${mapId}/entries/${entryId}/image`,
    { headers: { "X-API-Key": state.key } });
  if (!response.ok) return null;
  const blob = await response.blob();
  const uri = await new Promise((resolve, reject) => {
    const reader = new FileReader();
    reader.onload = () => resolve(reader.result);
    reader.onerror = () => reject(reader.error);
    reader.readAsDataURL(blob);
  });
  const bitmap = await createImageBitmap(blob);
  return { uri, width: bitmap.width, height: bitmap.height };
}

async function entryPage(mapId, entryId) {
  const [entry, kp] = await Promise.all([
    api(`/v1/maps/${mapId}/entries/${entryId}`),
    api(`/v1/maps/${mapId}/entries/${entryId}/keypoints`)]);
  const image = kp.has_image ? await entryImage(mapId, entryId) : null;
  const T = entry.T_world_from_cam;
  const plot = h("div", { id: "keypoint-plot", class: "plot", style: "height: 430px" });
  const tagInput = h("input", { id: "tags", value: entry.tags.join(", "), size: 30 });
  const outcome = h("p", { id: "entry-outcome" });
  const retag = async () => {
    const tags = tagInput.value.split(",").map((t) => t.trim()).filter(Boolean);
    const updated = await api(`/v1/maps/${mapId}/entries/${entryId}`, {
      method: "PATCH", headers: { "Content-Type": "application/json" },
      body: JSON.stringify({ tags }),
    });
    outcome.className = "ok";
    outcome.textContent = `tags saved: ${updated.tags.join(", ") || "none"}`;
  };
  const remove = async () => {
    if (!confirm(`Delete entry ${entryId} from the map? The next query no longer retrieves it.`)) {
      outcome.textContent = "not deleted";
      return;
    }
    await api(`/v1/maps/${mapId}/entries/${entryId}`, { method: "DELETE" });
    location.hash = `#/maps/${mapId}`;
  };
  const nWithout = kp.without_point_x_px.length;
  show(h("h1", {}, `Entry ${entryId}`),
    h("p", {}, h("a", { href: `#/maps/${mapId}` }, "← map")),
    h("div", { class: "grid2" }, plot, h("div", { class: "card" },
      h("h2", {}, "Pose (z-up world)"),
      h("p", { class: "pose", id: "entry-pose" },
        `x ${fmt(entry.pose.x_m)} m, y ${fmt(entry.pose.y_m)} m, z ${fmt(T[11])} m, ` +
        `heading ${deg(entry.pose.yaw_rad)}`),
      h("p", { class: "muted", id: "entry-facts" }, `run ${entry.run_id ?? "-"} · ` +
        `${entry.n_points} keypoints with a 3D point` +
        (image ? `, ${nWithout} without` : "") + ` · image ${entry.image_width_px}×` +
        `${entry.image_height_px} px · t ${entry.timestamp_s ?? "-"} s`),
      h("h2", {}, "Tags"), tagInput, " ",
      h("button", { id: "retag", onclick: () => retag().catch(fail) }, "Save tags"),
      h("h2", {}, "Delete"),
      h("button", { id: "delete", class: "danger", onclick: () => remove().catch(fail) },
        "Delete entry…"),
      outcome)),
    h("p", { class: "muted", id: "image-note" }, image
      ? "Keypoints on the entry's image: coloured by the depth of their 3D point in the " +
        "entry's camera; grey crosses got no 3D point (the map does not keep them)."
      : "This entry has no stored image (added before monoloc kept entry images): its " +
        "keypoints with a 3D point, coloured by depth."));
  const traces = [];
  if (image) {
    // pixel (0, 0) is the centre of the top-left pixel, in both images
    const dx = entry.image_width_px / image.width, dy = entry.image_height_px / image.height;
    traces.push({ type: "image", name: "image", source: image.uri, hoverinfo: "skip",
      x0: (dx - 1) / 2, y0: (dy - 1) / 2, dx, dy });
    traces.push({ type: "scattergl", mode: "markers", name: "keypoints without a 3D point",
      meta: { kind: "without" }, x: kp.without_point_x_px, y: kp.without_point_y_px,
      marker: { symbol: "x", size: 5, color: "#cfd8dc", opacity: 0.8 } });
  }
  traces.push({ type: "scattergl", mode: "markers", name: "keypoints with a 3D point",
    meta: { kind: "with" }, x: kp.x_px, y: kp.y_px,
    marker: { size: 6, color: kp.depth_m, colorscale: "Viridis", showscale: true,
      line: { color: "#000", width: 0.5 }, colorbar: { title: { text: "depth (m)" } } } });
  await Plotly.newPlot(plot, traces, plotLayout({
    xaxis: { range: [0, kp.image_width_px], title: { text: "u (px)" }, zeroline: false },
    yaxis: { range: [kp.image_height_px, 0], title: { text: "v (px)" }, scaleanchor: "x",
      zeroline: false },
    showlegend: false, plot_bgcolor: "#111",
  }), PLOT_CONFIG);
}

// ---- add images -------------------------------------------------------------------------

function addPage(mapId) {
  const images = h("input", { id: "images", type: "file", accept: "image/png,image/jpeg", multiple: true });
  const sources = h("input", { id: "sources", type: "file", multiple: true });
  const poses = h("textarea", { id: "poses", placeholder: "one line per image: 16 numbers of " +
    "T_world_from_cam, row-major (z-up world)" });
  const times = h("textarea", { id: "timestamps", rows: 2, placeholder: "optional: one " +
    "capture time per image, in seconds (same order as the poses)" });
  const tags = h("input", { id: "add-tags", value: "night" });
  const depthScale = h("input", { id: "depth-scale", type: "number", value: 5000 });
  const lidarT = h("input", { id: "lidar-T", size: 50, placeholder: "T_cam_from_lidar: 16 numbers" });
  const results = h("tbody", { id: "add-results" });
  const submit = async (event) => {
    event.preventDefault();
    const files = [...images.files];
    const lines = poses.value.split("\n").map((l) => l.trim()).filter(Boolean);
    const stamps = times.value.split("\n").map((l) => l.trim()).filter(Boolean);
    const byName = new Map([...sources.files].map((f) => [f.name.replace(/\.[^.]*$/, ""), f]));
    results.replaceChildren();
    for (const [i, file] of files.entries()) {
      const cell = h("td", { class: "outcome" }, "uploading…");
      results.append(h("tr", {}, h("td", {}, file.name), cell));
      try {
        if (!lines[i]) throw new Error(`no pose line for image ${i + 1}`);
        const form = new FormData();
        form.append("image", file);
        form.append("T_world_from_cam", lines[i]);
        if (tags.value.trim()) form.append("tags", tags.value.trim());
        if (stamps.length && !stamps[i]) throw new Error(`no capture time for image ${i + 1}`);
        if (stamps[i]) form.append("timestamp_s", stamps[i]);
        const source = byName.get(file.name.replace(/\.[^.]*$/, "")) || sources.files[i];
        if (source && source.name.endsWith(".bin")) {
          form.append("lidar", source);
          form.append("T_cam_from_lidar", lidarT.value);
        } else if (source) {
          form.append("depth", source);
          form.append("depth_scale", depthScale.value);
        }
        const made = await api(`/v1/maps/${mapId}/entries`, { method: "POST", body: form });
        cell.className = "outcome ok";
        cell.textContent = made.created
          ? `added: entry ${made.entry.id}, ${made.entry.n_points} points, tags ${made.entry.tags.join(", ")}`
          : `already in the map: entry ${made.entry.id}`;
      } catch (e) {
        cell.className = "outcome error";
        cell.textContent = `refused: ${e.message}`;
      }
    }
  };
  show(h("h1", {}, `Add images to map ${mapId}`),
    h("p", {}, h("a", { href: `#/maps/${mapId}` }, "← map")),
    h("form", { class: "card", onsubmit: (e) => submit(e).catch(fail) },
      h("p", {}, h("label", {}, "Images (PNG/JPEG, the map camera's size) ", images)),
      h("p", {}, h("label", {}, "Depth PNGs or LiDAR .bin scans (same names as the images, or the " +
        "same order) ", sources)),
      h("p", {}, h("label", {}, "Poses ", poses)),
      h("p", {}, h("label", {}, "Capture times (s) ", times)),
      h("p", {}, h("label", {}, "Tags ", tags), " ",
        h("label", {}, "depth scale (units per metre) ", depthScale)),
      h("p", {}, h("label", {}, "LiDAR extrinsics ", lidarT)),
      h("button", { id: "upload", class: "primary", type: "submit" }, "Upload")),
    h("table", {}, h("thead", {}, h("tr", {}, h("th", {}, "image"), h("th", {}, "outcome"))), results));
}

// ---- jobs --------------------------------------------------------------------------------

async function jobsPage() {
  const body = h("tbody", {});
  show(h("h1", {}, "Jobs"), h("p", { class: "muted" }, "Updated every second."),
    h("table", { id: "jobs" }, h("thead", {}, h("tr", {},
      ["id", "kind", "map", "state", "progress", "message", ""].map((t) => h("th", {}, t)))), body));
  const act = (id, what) => api(`/v1/jobs/${id}/${what}`, { method: "POST" }).then(refresh).catch(fail);
  async function refresh() {
    const jobs = (await api("/v1/jobs?limit=50")).items;
    body.replaceChildren(...jobs.map((j) => {
      const pct = Math.round(j.progress * 100);
      const actions = [];
      if (j.state === "interrupted" || j.state === "failed") {
        actions.push(h("button", { class: "resume", onclick: () => act(j.id, "resume") }, "resume"));
      }
      if (j.state === "queued" || j.state === "running") {
        actions.push(h("button", { class: "cancel", onclick: () => act(j.id, "cancel") }, "cancel"));
      }
      return h("tr", { "data-job-id": j.id, "data-state": j.state, "data-progress": pct },
        h("td", {}, j.id), h("td", {}, j.kind), h("td", {}, j.map_id ?? "-"),
        h("td", { class: "state" }, j.state),
        h("td", {}, h("progress", { max: 100, value: pct }), ` ${pct} %`),
        h("td", { class: j.error ? "error" : "muted" }, j.error || j.message), h("td", {}, actions));
    }));
  }
  await refresh();
  every(1000, refresh);
}

// ---- live vehicles -------------------------------------------------------------------------

// Server-sent events read with fetch (EventSource cannot send the X-API-Key header).
async function readEvents(path, onData, signal) {
  while (!signal.aborted) {
    try {
      const response = await fetch(path, { headers: { "X-API-Key": state.key }, signal });
      if (!response.ok) throw new ApiError(response.status, response.statusText);
      const reader = response.body.getReader();
      const decoder = new TextDecoder();
      let buffer = "";
      for (;;) {
        const { value, done } = await reader.read();
        if (done) break;
        buffer += decoder.decode(value, { stream: true });
        let cut;
        while ((cut = buffer.indexOf("\n\n")) >= 0) {
          const event = buffer.slice(0, cut);
          buffer = buffer.slice(cut + 2);
          const data = event.split("\n").filter((l) => l.startsWith("data:"))
            .map((l) => l.slice(5)).join("\n");
          if (data) onData(JSON.parse(data));
        }
      }
    } catch (e) {
      if (signal.aborted) return;
      setStatus(`live feed: ${e.message}; reconnecting`);
      await new Promise((r) => setTimeout(r, 1000));
    }
  }
}

async function livePage(mapId) {
  const poses = await api(`/v1/maps/${mapId}/poses`);
  const plot = h("div", { id: "live-plot", class: "plot" });
  const body = h("tbody", {});
  show(h("h1", {}, `Live vehicles on map ${mapId}`),
    h("p", {}, h("a", { href: `#/maps/${mapId}` }, "← map")),
    plot,
    h("table", { id: "vehicles" }, h("thead", {}, h("tr", {},
      ["vehicle", "key", "connected", "frames", "rate", "latency p50 / max", "estimate",
        "hypotheses", "dropped / errors"].map((t) => h("th", {}, t)))), body));
  const base = entryTraces(poses, () => true, { colour: "#b0bec5", size: 8, opacity: 0.6 });
  const trails = new Map();
  await Plotly.newPlot(plot, base, plotLayout(), PLOT_CONFIG);

  function update(snapshot) {
    const traces = [...base];
    body.replaceChildren();
    snapshot.vehicles.forEach((v, k) => {
      const colour = VEHICLE_COLOURS[k % VEHICLE_COLOURS.length];
      const key = `${v.replica}/${v.vehicle_id}`;  // ids are per replica
      const trail = trails.get(key) || [];
      const e = v.estimate;
      if (e && (!trail.length || trail[trail.length - 1].seq !== v.last_seq)) {
        trail.push({ x: e.x_m, y: e.y_m, seq: v.last_seq });
        if (trail.length > 500) trail.shift();
      }
      trails.set(key, trail);
      const label = `${v.name} #${v.vehicle_id}`;
      traces.push({ type: "scatter", mode: "lines", name: `${label} track`, showlegend: false,
        x: trail.map((p) => p.x), y: trail.map((p) => p.y), line: { color: colour, width: 2 } });
      traces.push({ type: "scatter", mode: "markers", name: `${label} hypotheses`,
        x: v.hypotheses.map((p) => p.x_m), y: v.hypotheses.map((p) => p.y_m),
        text: v.hypotheses.map((p) => `entry ${p.entry_id}, ${p.n_inliers} inliers`),
        marker: { symbol: "x", size: 8, color: colour, opacity: 0.6 } });
      if (e) {
        traces.push({ type: "scatter", mode: "markers", name: label,
          meta: { vehicle_id: v.vehicle_id, seq: v.last_seq },
          x: [e.x_m], y: [e.y_m], text: [`${label}: ${v.estimate_source}`],
          marker: { symbol: "arrow", size: 20, color: colour, line: { color: "#000", width: 1 },
            angle: e.yaw_rad === null ? 0 : 90 - e.yaw_rad * 180 / Math.PI } });
      }
      body.append(h("tr", { "data-vehicle-id": v.vehicle_id, "data-frames": v.frames },
        h("td", {}, h("span", { style: `color:${colour}` }, "■ "), label), h("td", {}, v.name),
        h("td", {}, v.connected ? `yes, ${fmt(v.connected_for_s, 0)} s` : "no"),
        h("td", { class: "frames" }, v.frames),
        h("td", { class: "rate" }, `${fmt(v.frame_rate_hz, 1)} Hz`),
        h("td", {}, `${fmt(v.latency_ms_p50, 1)} / ${fmt(v.latency_ms_max, 1)} ms`),
        h("td", { class: "pose" }, e ? `${fmt(e.x_m)}, ${fmt(e.y_m)} m, ${deg(e.yaw_rad)} ` +
          `(${v.estimate_source})` : "-"),
        h("td", {}, v.hypotheses.length), h("td", {}, `${v.dropped} / ${v.errors}`)));
    });
    if (!snapshot.vehicles.length) {
      body.append(h("tr", {}, h("td", { colspan: 9, class: "muted" }, "no vehicle is streaming")));
    }
    Plotly.react(plot, traces, plotLayout(), PLOT_CONFIG);
  }
  const abort = new AbortController();
  state.aborts.push(abort);
  readEvents(`/v1/maps/${mapId}/vehicles/events`, update, abort.signal);
}

// ---- routing ----------------------------------------------------------------------------

function every(ms, fn) {
  state.timers.push(setInterval(() => fn().catch(fail), ms));
}

function fail(e) {
  if (e instanceof ApiError && e.status === 401) { signOut(); return; }
  setStatus(`error: ${e.message}`);
  const p = h("p", { class: "error", id: "page-error" }, e.message);
  view().append(p);
}

const ROUTES = [
  [/^#\/maps\/(\d+)\/entries\/(\d+)$/, entryPage, "write"],
  [/^#\/maps\/(\d+)\/add$/, addPage, "write"],
  [/^#\/maps\/(\d+)\/live$/, livePage, "read"],
  [/^#\/maps\/(\d+)$/, mapPage, "read"],
  [/^#\/maps$/, mapsPage, null],
  [/^#\/jobs$/, jobsPage, "write"],
];

async function route() {
  state.timers.forEach(clearInterval);
  state.aborts.forEach((a) => a.abort());
  state.timers = [];
  state.aborts = [];
  setStatus("");
  if (!state.caps) { signInPage(); return; }
  const hash = location.hash || "#/maps";
  for (const [pattern, page, needs] of ROUTES) {
    const match = hash.match(pattern);
    if (!match) continue;
    if (needs && !state.caps[needs]) {
      show(h("p", { class: "error", id: "page-error" },
        `this key may not open this page (it needs the ${needs === "admin" ? "admin" : "map:write"} scope)`));
      return;
    }
    try { await page(...match.slice(1).map(Number)); } catch (e) { fail(e); }
    return;
  }
  location.hash = "#/maps";
}

async function start() {
  $("#signout").addEventListener("click", signOut);
  window.addEventListener("hashchange", route);
  const saved = sessionStorage.getItem(KEY_STORE);
  if (saved) {
    try { await signIn(saved); } catch (e) { sessionStorage.removeItem(KEY_STORE); }
  }
  await route();
}

start();
