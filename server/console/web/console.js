// The placedb console: five views over the server's JSON API (POST /api/v1/<Method>, protobuf
// JSON with the proto's field names; docs/console.md). No framework, no external requests.
"use strict";

const TOKEN_KEY = "placedb.token";
const COLORS = { kept: "#43d17a", dropped: "#ff5252", box: "#ffb300", line: "#4fc3f7" };
let refreshTimer = null;  // the live view's next refresh
let liveGeneration = 0;   // bumped when the view changes: the live loop stops

// ---- API ----------------------------------------------------------------------------------------

class ApiError extends Error {
  constructor(status, code, message) {
    super(message);
    this.status = status;
    this.code = code;
  }
}

function authHeaders() {
  const token = sessionStorage.getItem(TOKEN_KEY);
  return token ? { Authorization: "Bearer " + token } : {};
}

async function api(method, request) {
  const response = await fetch("/api/v1/" + method, {
    method: "POST",
    headers: Object.assign({ "Content-Type": "application/json" }, authHeaders()),
    body: JSON.stringify(request || {}),
  });
  let body = null;
  try {
    body = await response.json();
  } catch (e) {
    body = { code: "HTTP_" + response.status, message: response.statusText };
  }
  if (!response.ok) throw new ApiError(response.status, body.code, body.message);
  return body;
}

function showError(error) {
  const status = document.getElementById("status");
  status.className = "status";
  if (error.status === 401) {
    status.textContent = "The server needs a token (" + error.message + "). Paste one in the " +
        "Token field above: it is kept for this tab only.";
  } else if (error.status === 403) {
    status.textContent = "Not allowed: " + error.message;
  } else {
    status.textContent = (error.code || "error") + ": " + error.message;
  }
}

function showInfo(text) {
  const status = document.getElementById("status");
  status.className = text ? "status info" : "status hidden";
  status.textContent = text || "";
}

function clearStatus() {
  showInfo("");
}

// ---- DOM helpers --------------------------------------------------------------------------------

function el(tag, attributes, ...children) {
  const node = document.createElement(tag);
  for (const [key, value] of Object.entries(attributes || {})) {
    if (key === "class") node.className = value;
    else if (key.startsWith("on")) node.addEventListener(key.slice(2), value);
    else if (key === "dataset") Object.assign(node.dataset, value);
    else node.setAttribute(key, value);
  }
  for (const child of children.flat()) {
    if (child === null || child === undefined) continue;
    node.append(child instanceof Node ? child : document.createTextNode(String(child)));
  }
  return node;
}

function bytes(n) {
  n = Number(n || 0);
  const units = ["B", "KiB", "MiB", "GiB", "TiB"];
  let i = 0;
  while (n >= 1024 && i < units.length - 1) {
    n /= 1024;
    i++;
  }
  return (i ? n.toFixed(1) : n) + " " + units[i];
}

function time(ns) {
  const ms = Number(ns || 0) / 1e6;
  return ms > 0 ? new Date(ms).toISOString().replace("T", " ").slice(0, 19) : "-";
}

// The proto's names of enum values ("agent" for BOX_SOURCE_UNSPECIFIED: its (name) option), as
// the CLI prints them; the server serves them (/enum-names.json) and start() loads them once.
let enumNames = {};
// The same names by number (/enum-numbers.json), for the int32 fields the proto names by an enum
// (COCO class ids).
let enumNumbers = {};

function enumName(value, type) {
  if (value === undefined || value === null) return "-";
  const name = (enumNames[type] || {})[value];
  return name === undefined ? String(value) : name;
}

function className(classId) {
  const name = (enumNumbers.CocoClass || {})[String(classId)];
  return name === undefined ? "class " + classId : name;
}

function loadImage(src) {
  return new Promise((resolve, reject) => {
    const image = new Image();
    image.onload = () => resolve(image);
    image.onerror = () => reject(new Error("cannot load the image"));
    image.src = src;
  });
}

function jpegUrl(base64) {
  return "data:image/jpeg;base64," + base64;
}

// ---- Drawing ------------------------------------------------------------------------------------

function drawKeypoints(context, keypoints, scale, color, ox = 0, oy = 0) {
  context.fillStyle = color;
  for (const k of keypoints || []) {
    context.fillRect(ox + (k.x || 0) * scale - 1.5, oy + (k.y || 0) * scale - 1.5, 3, 3);
  }
}

function drawBoxes(context, boxes, scale, ox = 0, oy = 0) {
  context.strokeStyle = COLORS.box;
  context.lineWidth = 2;
  context.font = "11px sans-serif";
  context.fillStyle = COLORS.box;
  for (const box of boxes || []) {
    const r = box.rect || {};
    context.strokeRect(ox + (r.x || 0) * scale, oy + (r.y || 0) * scale, (r.width || 0) * scale,
                       (r.height || 0) * scale);
    context.fillText(box.class_name || "", ox + (r.x || 0) * scale + 2, oy + (r.y || 0) * scale + 12);
  }
}

// The place's frame as the console shows it: its thumbnail (when the map keeps them) with the
// dynamic-object boxes, the kept (green) and dropped (red) keypoints; else a placeholder.
async function placeCanvas(map, place) {
  const canvas = el("canvas", { width: 320, height: 240, class: "place-canvas" });
  const context = canvas.getContext("2d");
  const thumbnail = place.thumbnail;
  if (thumbnail && thumbnail.jpeg) {
    const image = await loadImage(jpegUrl(thumbnail.jpeg));
    canvas.width = image.width;
    canvas.height = image.height;
    context.drawImage(image, 0, 0);
    const scale = image.width / Math.max(1, thumbnail.source_width || image.width);
    drawBoxes(context, place.boxes_used, scale);
    const features = place.features || place.sift_features || {};
    drawKeypoints(context, features.keypoints, scale, COLORS.kept);
    drawKeypoints(context, thumbnail.dropped_keypoints, scale, COLORS.dropped);
    canvas.dataset.thumbnail = "yes";
  } else {
    placeholderCanvas(canvas, "no thumbnail", "(this map keeps none: MapConfig.thumbnails)");
    canvas.dataset.thumbnail = "no";
  }
  return canvas;
}

function placeholderCanvas(canvas, title, subtitle) {
  canvas = canvas || el("canvas", { width: 320, height: 240, class: "place-canvas" });
  const context = canvas.getContext("2d");
  context.fillStyle = "#2b3036";
  context.fillRect(0, 0, canvas.width, canvas.height);
  context.fillStyle = "#aab2bd";
  context.font = "14px sans-serif";
  context.textAlign = "center";
  context.fillText(title, 160, 112);
  context.font = "11px sans-serif";
  context.fillText(subtitle, 160, 132);
  return canvas;
}

// At most `limit` calls of fn() at once (the others queue, in order): a page's GetPlace calls
// run in parallel without queueing a thousand requests in the browser.
function limiter(limit) {
  let running = 0;
  const waiting = [];
  const next = () => {
    if (running >= limit || !waiting.length) return;
    running++;
    const { fn, resolve, reject } = waiting.shift();
    fn().then(resolve, reject).finally(() => {
      running--;
      next();
    });
  };
  return (fn) => new Promise((resolve, reject) => {
    waiting.push({ fn, resolve, reject });
    next();
  });
}
const placeCalls = limiter(4);

function legend() {
  const item = (color, text) => {
    const swatch = el("span", { class: "swatch" });
    swatch.style.background = color;
    return el("span", {}, swatch, text);
  };
  return el("div", { class: "legend" }, item(COLORS.kept, "kept (static) keypoints"),
            item(COLORS.dropped, "dropped (dynamic) keypoints"),
            item(COLORS.box, "dynamic-object boxes"));
}

function placeMeta(place) {
  const counts = place.counts || {};
  const metadata = place.metadata || {};
  return el("div", { class: "meta" },
            el("strong", {}, "place " + place.place_id), " · ", metadata.agent_id || "-", " #",
            metadata.sequence || 0, el("br"), time(metadata.timestamp_ns), el("br"),
            "kept ", counts.kept || 0, " · dropped ", counts.dynamic || 0,
            " · coverage ", ((counts.dynamic_coverage || 0) * 100).toFixed(1), "%");
}

// A place's card, shown at once from what the listing says (metadata, counts); its frame is
// drawn when its GetPlace answers (card.ready resolves then; data-state loading -> loaded). Only
// a map that keeps thumbnails (or a listing without metadata) needs the GetPlace.
function placeCard(map, place, thumbnails) {
  const id = place.place_id;
  const card = el("div", { class: "card place-card", dataset: { placeId: String(id), state: "loading" } },
                  placeholderCanvas(null, "loading…", "place " + id), placeMeta(place));
  card.firstChild.dataset.thumbnail = "loading";
  card.ready = (async () => {
    let full = place;
    if (thumbnails || !place.metadata) {
      try {
        full = await placeCalls(() => api("GetPlace", { map, place_id: id, include_thumbnail: true,
                                                         include_features: true }));
      } catch (e) {
        // The listing's metadata is still worth showing.
      }
    }
    let canvas;
    try {
      canvas = await placeCanvas(map, full);
    } catch (e) {
      canvas = placeholderCanvas(null, "cannot draw", e.message);
      canvas.dataset.thumbnail = "error";
    }
    card.replaceChildren(canvas, placeMeta(full));
    card.dataset.state = "loaded";
  })();
  return card;
}

// ---- Views --------------------------------------------------------------------------------------

// Which vocabulary a map uses and where it came from (issue 29: maps learn their own).
function vocabularyText(description) {
  const vocabulary = description && description.vocabulary;
  if (!vocabulary || !vocabulary.current) return "-";
  const current = vocabulary.current;
  const shape = "k=" + (current.branching || 0) + " L=" + (current.depth || 0);
  const parts = [current.origin + " " + current.checksum + " (" + shape + ")"];
  if (current.origin === "learned") {
    parts.push(el("div", { class: "muted" }, "learned " + new Date(Number(current.learned_unix_ms)).toLocaleString() +
                  " from " + Number(current.descriptors_sampled || 0) + " descriptors of " +
                  Number(current.places_sampled || 0) + " places"));
  }
  if (vocabulary.previous) {
    parts.push(el("div", { class: "muted" }, "previous: " + vocabulary.previous.origin + " " +
                  vocabulary.previous.checksum));
  }
  if (vocabulary.switching) parts.push(el("div", {}, "switching…"));
  return parts;
}

async function mapsView(view) {
  view.append(el("h2", {}, "Maps"));
  const list = await api("ListMaps", {});
  const maps = list.maps || [];
  if (!maps.length) {
    view.append(el("p", { class: "muted" }, "No maps yet (placedb maps create NAME)."));
    return;
  }
  const table = el("table", { id: "maps-table" },
                   el("tr", {}, ["map", "state", "features", "places", "descriptors kept",
                                 "dropped", "on disk", "detector", "thumbnails", "vocabulary",
                                 "settings"]
                                    .map((h) => el("th", {}, h))));
  view.append(table);
  // Every map's GetMap at once (an unavailable map still gets its row).
  const descriptions = await Promise.all(
      maps.map((summary) => api("GetMap", { name: summary.name }).catch(() => null)));
  for (const [i, summary] of maps.entries()) {
    const description = descriptions[i];
    const stats = (description && description.stats) || {};
    const config = (description && description.config) || {};
    const detection = config.detection || {};
    const link = el("a", { href: "#/places/" + encodeURIComponent(summary.name) }, summary.name);
    table.append(el("tr", { class: "map-row", dataset: { map: summary.name } },
                    el("td", {}, link),
                    el("td", {}, enumName(summary.state, "MapState"),
                       summary.unavailable_reason ? el("div", { class: "muted" }, summary.unavailable_reason) : null),
                    el("td", {}, enumName(summary.feature_type, "FeatureType")),
                    el("td", { class: "num" }, Number(summary.places || 0)),
                    el("td", { class: "num" }, Number(stats.descriptors_kept || 0)),
                    el("td", { class: "num" }, Number(stats.descriptors_dropped || 0)),
                    el("td", { class: "num" }, bytes(stats.bytes_on_disk)),
                    el("td", {}, detection.enabled === false ? "off" : "on",
                       " (", enumName(detection.box_source, "BoxSource"), ")"),
                    el("td", {}, config.thumbnails && config.thumbnails.enabled ? "kept" : "off"),
                    el("td", { class: "vocabulary" }, vocabularyText(description)),
                    el("td", {}, el("details", {}, el("summary", {}, "config"),
                                    el("pre", {}, JSON.stringify(config, null, 1))))));
  }
}

// `startAt`: a place id to start at (a link from the dynamics page), highlighted; 0 = the newest.
async function placesView(view, map, startAt = 0) {
  view.append(el("h2", {}, "Places of ", el("span", { id: "places-map" }, map)));
  const description = await api("GetMap", { name: map });
  const agents = (description.agents || []).map((a) => a.agent_id);
  // Any agent id may be typed; the ones GetMap reports are offered.
  const agent = el("input", { id: "filter-agent", list: "agent-ids", placeholder: "every agent" });
  const agentIds = el("datalist", { id: "agent-ids" }, agents.map((a) => el("option", { value: a })));
  const from = el("input", { type: "datetime-local", id: "filter-from" });
  const to = el("input", { type: "datetime-local", id: "filter-to" });
  const limit = el("input", { type: "number", id: "filter-limit", value: "24", min: "1", max: "1000" });
  const cards = el("div", { class: "cards", id: "places" });
  const more = el("button", { class: "plain", id: "places-next" }, "Older");
  const info = el("p", { class: "muted", id: "places-info" });
  let before = 0;
  const thumbnails = Boolean(description.config && description.config.thumbnails &&
                             description.config.thumbnails.enabled);
  const ns = (input) => (input.value ? String(new Date(input.value).getTime() * 1e6) : "0");

  async function page(reset) {
    cards.dataset.loaded = "";
    if (reset) {
      before = startAt ? startAt + 1 : 0;
      cards.replaceChildren();
    }
    more.disabled = true;
    let places = [];
    try {
      const response = await api("ListPlaces", {
        map, agent_id: agent.value, from_timestamp_ns: ns(from), to_timestamp_ns: ns(to),
        limit: Number(limit.value) || 24, before_place_id: before,
      });
      places = response.places || [];
      before = response.next_before_place_id || 0;
    } catch (e) {
      if (e.status !== 501) throw e;
      // A server without ListPlaces: the newest ids one by one (no filters).
      info.textContent = "This server does not list places yet (ListPlaces: " +
          (e.message || e.code) + "): showing the newest ids, without filters.";
      const newest = before || Number((description.stats || {}).places || 0);
      const count = Math.min(Number(limit.value) || 24, newest);
      for (let id = newest; id > newest - count; id--) places.push({ place_id: id });
      before = newest - count;
    }
    // Every card at once from the listing, their frames drawn as their GetPlace calls answer.
    const added = places.map((place) => placeCard(map, place, thumbnails));
    for (const card of added) card.classList.toggle("chosen", Number(card.dataset.placeId) === startAt);
    cards.append(...added);
    if (!cards.children.length) cards.append(el("p", { class: "muted" }, "No places match."));
    more.disabled = before === 0;
    await Promise.all(added.map((card) => card.ready));
    cards.dataset.loaded = "yes";  // for the browser test: every card drawn
  }
  const form = el("form", { class: "bar", onsubmit: (event) => {
    event.preventDefault();
    page(true).catch(showError);
  } },
                  el("label", {}, "agent", agent, agentIds), el("label", {}, "from", from),
                  el("label", {}, "to", to), el("label", {}, "per page", limit),
                  el("button", { type: "submit" }, "Show"));
  more.addEventListener("click", () => page(false).catch(showError));
  view.append(form, legend(), info);
  if (!thumbnails) {
    view.append(el("p", { class: "muted" }, "This map keeps no thumbnails: places show a placeholder."));
  }
  view.append(cards, el("p", {}, more));
  await page(true);
}

function fileToBase64(file) {
  return new Promise((resolve, reject) => {
    const reader = new FileReader();
    reader.onload = () => resolve(String(reader.result).split(",", 2)[1]);
    reader.onerror = () => reject(new Error("cannot read " + file.name));
    reader.readAsDataURL(file);
  });
}

// The query image and one match side by side, inlier correspondences joined by lines.
async function matchCanvas(queryImage, queryWidth, response, map, match) {
  const place = await api("GetPlace", { map, place_id: match.place_id, include_thumbnail: true,
                                        include_features: true });
  const height = 240;
  const qScale = queryImage ? height / queryImage.height : height / Math.max(1, response.image_height);
  const qWidth = Math.round((queryImage ? queryImage.width : queryWidth) * qScale) || 320;
  const thumbnail = place.thumbnail;
  let placeImage = null;
  if (thumbnail && thumbnail.jpeg) placeImage = await loadImage(jpegUrl(thumbnail.jpeg));
  const features = place.features || place.sift_features || {};
  const sourceWidth = (thumbnail && thumbnail.source_width) || features.image_width || 640;
  const sourceHeight = (thumbnail && thumbnail.source_height) || features.image_height || 480;
  const pScale = height / sourceHeight;
  const pWidth = Math.round(sourceWidth * pScale);
  const canvas = el("canvas", { width: qWidth + 16 + pWidth, height });
  const context = canvas.getContext("2d");
  context.fillStyle = "#2b3036";
  context.fillRect(0, 0, canvas.width, height);
  if (queryImage) context.drawImage(queryImage, 0, 0, qWidth, height);
  if (placeImage) context.drawImage(placeImage, qWidth + 16, 0, pWidth, height);
  const queryKeypoints = response.query_keypoints || [];
  const placeKeypoints = features.keypoints || [];
  if (!placeImage) {
    // No thumbnail kept: the place's stored keypoints alone show its structure.
    drawKeypoints(context, placeKeypoints, pScale, COLORS.kept, qWidth + 16, 0);
    context.fillStyle = "#aab2bd";
    context.font = "11px sans-serif";
    context.fillText("place " + match.place_id + ": no thumbnail kept", qWidth + 24, height - 8);
  }
  drawKeypoints(context, queryKeypoints, qScale, COLORS.kept);
  drawKeypoints(context, response.query_dropped_keypoints, qScale, COLORS.dropped);
  drawBoxes(context, response.boxes_used, qScale);
  drawBoxes(context, place.boxes_used, pScale, qWidth + 16, 0);
  context.strokeStyle = COLORS.line;
  context.lineWidth = 1;
  let lines = 0;
  for (const c of match.correspondences || []) {
    const q = queryKeypoints[c.query_keypoint || 0];
    const p = placeKeypoints[c.place_keypoint || 0];
    if (!q || !p) continue;
    context.beginPath();
    context.moveTo((q.x || 0) * qScale, (q.y || 0) * qScale);
    context.lineTo(qWidth + 16 + (p.x || 0) * pScale, (p.y || 0) * pScale);
    context.stroke();
    lines++;
  }
  canvas.dataset.lines = String(lines);
  return canvas;
}

// A verified match's relative pose (issue 32) as the CLI prints it: T_place_query's translation
// (metres with depth on either side, else a unit direction), its rotation angle, the solver.
function formatPose(pose) {
  const t = (pose.transform || []).map(Number);
  if (t.length !== 16) return "malformed (" + t.length + " transform values)";
  const cos = Math.min(1, Math.max(-1, (t[0] + t[5] + t[10] - 1) / 2));
  const degrees = Math.acos(cos) * 180 / Math.PI;
  return "t (" + [t[3], t[7], t[11]].map((v) => v.toFixed(3)).join(", ") + ")" +
         (pose.metric ? " m" : " (direction)") + ", " + degrees.toFixed(2) + " deg, " +
         (pose.solver || "") + ", " + (pose.inliers || 0) + " inliers, rms " +
         Number(pose.rms_error_px || 0).toFixed(2) + " px";
}

// "fx,fy,cx,cy" (pixels) as an Observation.camera; null when empty; an Error naming the field
// when malformed.
function parseCamera(text) {
  if (!text.trim()) return null;
  const values = text.split(",").map((v) => Number(v.trim()));
  if (values.length !== 4 || values.some((v) => !Number.isFinite(v))) {
    throw new Error("camera: expected fx,fy,cx,cy (4 numbers, pixels), got '" + text + "'");
  }
  return { fx: values[0], fy: values[1], cx: values[2], cy: values[3] };
}

function timingsTable(timings) {
  const stages = ["queue", "decode", "detect", "refine", "extract", "depth", "filter", "transform",
                  "search", "verify", "pose", "total"];
  return el("table", { id: "query-timings" },
            el("tr", {}, stages.map((s) => el("th", {}, s))),
            el("tr", {}, stages.map((s) => el("td", { class: "num" },
                                              Number((timings || {})[s + "_ms"] || 0).toFixed(1)))));
}

function splitChart(counts) {
  const kept = Number(counts.kept || 0);
  const dropped = Number(counts.dynamic || 0) + Number(counts.depth_removed || 0);
  const total = Math.max(1, kept + dropped);
  const keptBar = el("div", { class: "kept" });
  keptBar.style.width = (100 * kept / total) + "%";
  const droppedBar = el("div", { class: "dropped" });
  droppedBar.style.width = (100 * dropped / total) + "%";
  return el("div", { id: "query-split" },
            el("div", { class: "bar-chart" }, keptBar, droppedBar),
            el("div", { class: "muted" }, "SC (kept) ", kept, " · DC (dropped) ", dropped, " of ",
               Number(counts.total || 0), " · dynamic coverage ",
               ((counts.dynamic_coverage || 0) * 100).toFixed(1), "%"));
}

async function queryView(view) {
  view.append(el("h2", {}, "Query"));
  const list = await api("ListMaps", {});
  const maps = (list.maps || []).filter((m) => m.available);
  const map = el("select", { id: "query-map" }, maps.map((m) => el("option", { value: m.name }, m.name)));
  const file = el("input", { type: "file", id: "query-file", accept: "image/jpeg,image/png" });
  const placeId = el("input", { type: "number", id: "query-place", min: "1", placeholder: "or a stored place id" });
  const topK = el("input", { type: "number", id: "query-top-k", value: "5", min: "1", max: "100" });
  const verifiedOnly = el("input", { type: "checkbox", id: "query-verified-only" });
  const excludeAgent = el("input", { type: "checkbox", id: "query-exclude-agent" });
  const camera = el("input", { type: "text", id: "query-camera", size: "18",
                               placeholder: "fx,fy,cx,cy" });
  const drop = el("div", { class: "drop", id: "query-drop" }, "Drop an image here, or ", file);
  const results = el("div", { id: "query-results" });
  let dropped = null;
  drop.addEventListener("dragover", (event) => {
    event.preventDefault();
    drop.classList.add("over");
  });
  drop.addEventListener("dragleave", () => drop.classList.remove("over"));
  drop.addEventListener("drop", (event) => {
    event.preventDefault();
    drop.classList.remove("over");
    dropped = event.dataTransfer.files[0] || null;
    if (dropped) query();
  });
  file.addEventListener("change", () => {
    dropped = null;
    if (file.files.length) query();
  });

  // One query: any error ends the "Querying…" state with its message, in the results and in the
  // status line.
  async function query() {
    try {
      await run();
    } catch (error) {
      showError(error);
      results.replaceChildren(el("p", { class: "status", id: "query-error" },
                                 "Query failed: " + (error.code ? error.code + ": " : "") +
                                     error.message));
      results.dataset.done = "error";
    }
  }

  async function run() {
    clearStatus();
    results.dataset.done = "";
    results.replaceChildren(el("p", { class: "muted" }, "Querying…"));
    const chosen = dropped || file.files[0] || null;
    const observation = { agent_id: "console" };
    // The query's camera makes each verified match's relative pose (a stored place: its own).
    const typed = parseCamera(camera.value);
    if (typed) observation.camera = typed;
    let queryImage = null;
    let queryWidth = 0;
    if (chosen) {
      observation.encoded_image = { data: await fileToBase64(chosen) };
      queryImage = await loadImage(URL.createObjectURL(chosen));
    } else if (placeId.value) {
      // A stored place queries with its own stored features.
      const place = await api("GetPlace", { map: map.value, place_id: Number(placeId.value),
                                            include_features: true, include_thumbnail: true });
      if (place.features) observation.features = place.features;
      else if (place.sift_features) observation.sift_features = place.sift_features;
      if (!observation.camera && place.camera) observation.camera = place.camera;
      if (place.thumbnail && place.thumbnail.jpeg) queryImage = await loadImage(jpegUrl(place.thumbnail.jpeg));
      queryWidth = ((place.features || place.sift_features || {}).image_width) || 640;
    } else {
      results.replaceChildren(el("p", { class: "muted" }, "Choose an image or a place first."));
      return;
    }
    const response = await api("Query", {
      map: map.value, observation,
      options: { top_k: Number(topK.value) || 5, verified_only: verifiedOnly.checked,
                 exclude_same_agent: excludeAgent.checked, include_correspondences: true },
    });
    const matches = response.matches || [];
    results.replaceChildren(
        el("div", { class: "split" },
           el("div", {}, el("h3", {}, "DC/SC split"), splitChart(response.counts || {}),
              response.valid ? null : el("p", { class: "status" }, "invalid query: ", response.rejection)),
           el("div", {}, el("h3", {}, "Stage timings (ms)"), timingsTable(response.timings))),
        el("h3", {}, matches.length + " match" + (matches.length === 1 ? "" : "es")));
    for (const [rank, match] of matches.entries()) {
      const card = el("div", { class: "match" + (rank === 0 ? " top" : ""),
                               dataset: { placeId: String(match.place_id), rank: String(rank + 1) } },
                      el("div", {}, el("strong", {}, "#" + (rank + 1) + " place " + match.place_id),
                         " · score ", Number(match.score || 0).toFixed(4), " · inliers ",
                         match.inliers || 0, match.verified ? " · verified" : " · not verified",
                         " · ", (match.metadata || {}).agent_id || "-", " #",
                         (match.metadata || {}).sequence || 0));
      if (match.relative_pose) {
        card.append(el("div", { class: "pose" }, "pose: " + formatPose(match.relative_pose)));
      } else if (match.verified && match.pose_unavailable) {
        card.append(el("div", { class: "pose muted" }, "no pose: " + match.pose_unavailable));
      }
      results.append(card);
      try {
        card.append(await matchCanvas(queryImage, queryWidth, response, map.value, match));
      } catch (e) {
        card.append(el("p", { class: "muted" }, "cannot draw: " + e.message));
      }
    }
    results.dataset.done = "yes";
  }

  const form = el("form", { class: "bar", onsubmit: (event) => {
    event.preventDefault();
    query();
  } },
                  el("label", {}, "map", map), drop, el("label", {}, "stored place", placeId),
                  el("label", {}, "top-k", topK),
                  el("label", {}, "verified only", verifiedOnly),
                  el("label", {}, "exclude own agent", excludeAgent),
                  el("label", { title: "the query's camera, for relative poses" }, "camera",
                     camera),
                  el("button", { type: "submit", id: "query-run" }, "Query"));
  view.append(form, legend(), results);
}

async function liveView(view) {
  view.append(el("h2", {}, "Live"));
  const list = await api("ListMaps", {});
  const maps = (list.maps || []).filter((m) => m.available);
  const map = el("select", { id: "live-map" }, maps.map((m) => el("option", { value: m.name }, m.name)));
  const agents = el("div", { id: "live-agents" });
  const latest = el("div", { class: "cards", id: "live-places" });
  const stamp = el("span", { class: "muted", id: "live-updated" });
  view.append(el("div", { class: "bar" }, el("label", {}, "map", map), stamp),
              el("h3", {}, "Agents (ingest rate over the last 10 s)"), agents,
              el("h3", {}, "Latest places"), latest);
  let shown = "";  // the place ids on screen: redraw only when they change
  let cardsById = new Map();  // their cards, kept across refreshes (each place is fetched once)
  async function refresh() {
    if (!map.value) return;
    const name = map.value;
    // Both at once; the cards of new places are shown from the listing, their frames drawn as
    // their GetPlace calls answer (never awaited here: a refresh takes two calls' time).
    const [description, listed] = await Promise.all([
      api("GetMap", { name }),
      api("ListPlaces", { map: name, limit: 8 }).catch((e) => {
        if (e.status !== 501) throw e;
        return null;
      }),
    ]);
    if (name !== map.value) return;  // the map changed meanwhile
    const rows = (description.agents || []).map((a) => el("tr", { dataset: { agent: a.agent_id } },
        el("td", {}, a.agent_id), el("td", { class: "num" }, Number(a.frames_per_second || 0).toFixed(2)),
        el("td", { class: "num" }, Number(a.frames || 0)), el("td", { class: "num" }, Number(a.places || 0)),
        el("td", { class: "num" }, a.last_place_id || "-"),
        el("td", {}, a.last_frame_unix_ms ? new Date(Number(a.last_frame_unix_ms)).toISOString().slice(11, 19) : "-")));
    agents.replaceChildren(rows.length
        ? el("table", {}, el("tr", {}, ["agent", "frames/s", "frames", "places", "last place", "last frame (UTC)"]
                                          .map((h) => el("th", {}, h))), rows)
        : el("p", { class: "muted" }, "No agent has ingested into this map since the server started."));
    let places = listed ? listed.places || [] : [];
    if (!listed) {
      // A server without ListPlaces: the newest ids.
      const newest = Number((description.stats || {}).places || 0);
      for (let id = newest; id > Math.max(0, newest - 8); id--) places.push({ place_id: id });
    }
    const thumbnails = Boolean(description.config && description.config.thumbnails &&
                               description.config.thumbnails.enabled);
    const ids = places.map((p) => p.place_id).join(",");
    if (ids !== shown) {
      shown = ids;
      const cards = places.map((p) => cardsById.get(p.place_id) || placeCard(name, p, thumbnails));
      cardsById = new Map(cards.map((card, i) => [places[i].place_id, card]));
      latest.replaceChildren(...cards);
    }
    stamp.textContent = "updated " + new Date().toISOString().slice(11, 19) + " UTC";
  }
  map.addEventListener("change", () => {
    shown = "";
    cardsById = new Map();
    refresh().catch(showError);
  });
  await refresh();
  // The next refresh 1 s after this one ended: refreshes never pile up behind a slow server.
  const generation = ++liveGeneration;
  const tick = () => {
    refresh().then(clearStatus, showError).finally(() => {
      if (generation === liveGeneration) refreshTimer = setTimeout(tick, 1000);
    });
  };
  refreshTimer = setTimeout(tick, 1000);
}

// ---- Dynamics -----------------------------------------------------------------------------------

const WEEKDAYS = ["Mon", "Tue", "Wed", "Thu", "Fri", "Sat", "Sun"];
const RANKED_PER_PAGE = 24;

function percent(share) {
  return (Number(share || 0) * 100).toFixed(1) + "%";
}

function plural(n, word) {
  return Number(n) + " " + word + (Number(n) === 1 ? "" : "s");
}

// A card shown at once, saying it is loading; card.fill(...) puts its content in when its call
// answers (data-state loading -> loaded), card.fail(error) says why it has none.
function pendingCard(id, title) {
  const body = el("div", { class: "muted" }, "loading…");
  const card = el("div", { class: "card wide dynamics-card", id, dataset: { state: "loading" } },
                  el("h3", {}, title), body);
  card.fill = (...children) => {
    body.className = "";
    body.replaceChildren(...children.flat());
    card.dataset.state = "loaded";
  };
  card.fail = (error) => {
    body.className = "status";
    body.textContent = (error.code ? error.code + ": " : "") + error.message;
    card.dataset.state = "error";
  };
  return card;
}

// "person 3, car 1": each class with the frames it was seen in, most seen first.
function classesText(statistics) {
  const classes = [...((statistics || {}).classes || [])];
  classes.sort((a, b) => Number(b.frames || 0) - Number(a.frames || 0));
  return classes.map((c) => className(c.class_id) + " " + Number(c.frames || 0)).join(", ") || "none";
}

function totalsTable(statistics, invalid) {
  const row = (label, value) => el("tr", {}, el("th", {}, label), el("td", { class: "num" }, value));
  const s = statistics || {};
  return el("table", { id: "dynamics-totals" },
            row("frames (places' observations)", Number(s.observations || 0)),
            row("mean coverage", percent(s.mean_coverage)),
            row("max coverage", percent(s.max_coverage)),
            row("newest frame", time(s.last_timestamp_ns) + " · " + percent(s.last_coverage)),
            row("frames without a time", Number(s.untimed || 0)),
            row("boxes of unknown classes", Number(s.unknown_class_boxes || 0)),
            // Frames covered so much they kept too few features: they made no place.
            row("invalid frames (no place)", Number((invalid || {}).observations || 0) + " · mean " +
                percent((invalid || {}).mean_coverage)));
}

// Each class the map's frames showed: in how many frames (and their share), how many boxes. A
// row's button ranks the places by that class.
function classesTable(statistics, choose) {
  const observations = Math.max(1, Number(statistics.observations || 0));
  const classes = [...(statistics.classes || [])];
  classes.sort((a, b) => Number(b.frames || 0) - Number(a.frames || 0));
  if (!classes.length) return el("p", { class: "muted" }, "No dynamic objects in this map's frames.");
  return el("table", { id: "dynamics-classes" },
            el("tr", {}, ["class", "frames", "share of frames", "boxes", ""].map((h) => el("th", {}, h))),
            classes.map((c) => {
              const share = Number(c.frames || 0) / observations;
              const bar = el("div", { class: "share" });
              bar.style.width = (100 * share) + "%";
              return el("tr", { class: "class-row", dataset: { classId: String(c.class_id) } },
                        el("td", {}, className(c.class_id)),
                        el("td", { class: "num" }, Number(c.frames || 0)),
                        el("td", {}, el("div", { class: "share-bar", title: percent(share) }, bar),
                           " ", percent(share)),
                        el("td", { class: "num" }, Number(c.boxes || 0)),
                        el("td", {}, el("button", { class: "plain", onclick: () => choose(c.class_id) },
                                        "rank places")));
            }));
}

// Coverage by hour of day (UTC): a weekday x hour grid, each bin coloured by its mean coverage
// (darkest = the busiest bin), grey where no frame was taken; the frames per hour underneath.
function hoursChart(statistics) {
  const bins = (statistics.hours || []);
  if (!bins.length) {
    return el("p", { class: "muted" }, "No timed frames: the hours are unknown (frames without a " +
              "timestamp, or replayed with the wall clock, land in one hour).");
  }
  const byKey = new Map(bins.map((b) => [Number(b.weekday || 0) * 24 + Number(b.hour || 0), b]));
  const busiest = Math.max(...bins.map((b) => Number(b.mean_coverage || 0)), 1e-9);
  const perHour = new Array(24).fill(0);
  for (const b of bins) perHour[Number(b.hour || 0)] += Number(b.observations || 0);
  const grid = el("div", { class: "hours", id: "dynamics-hours" });
  grid.append(el("span", {}), ...Array.from({ length: 24 }, (_, h) => el("span", { class: "hour-label" }, h)));
  for (let day = 0; day < 7; day++) {
    grid.append(el("span", { class: "hour-label" }, WEEKDAYS[day]));
    for (let hour = 0; hour < 24; hour++) {
      const bin = byKey.get(day * 24 + hour);
      const cell = el("span", { class: "hour-cell" });
      if (bin) {
        const level = Number(bin.mean_coverage || 0) / busiest;
        // Light to the accent blue: the share of the busiest bin's coverage.
        cell.style.background = "rgba(31, 111, 235, " + (0.12 + 0.88 * level).toFixed(3) + ")";
        cell.title = WEEKDAYS[day] + " " + hour + " h: " + plural(bin.observations || 0, "frame") +
            ", mean coverage " + percent(bin.mean_coverage);
        cell.dataset.observations = String(Number(bin.observations || 0));
      } else {
        cell.title = WEEKDAYS[day] + " " + hour + " h: no frames";
      }
      grid.append(cell);
    }
  }
  grid.append(el("span", { class: "hour-label" }, "frames"),
              ...perHour.map((n) => el("span", { class: "hour-label" }, n || "")));
  return el("div", {}, grid,
            el("p", { class: "muted" }, "UTC; darkest = mean coverage " + percent(busiest) +
               "; grey = no frames at that hour."));
}

// One ranked place: its rank, score and classes at once, its frame (when the map keeps
// thumbnails) drawn when its GetPlace answers; it links to the place on the places page.
function rankedCard(map, ranked, rank, measure, thumbnails) {
  const id = ranked.place_id;
  const support = plural(ranked.support || 0, "frame");
  const scoreText = measure.label === null
      ? "mean coverage " + percent(ranked.score) + " over " + support
      : measure.label + " in " + percent(ranked.score) + " of " + support;
  const canvas = placeholderCanvas(null, thumbnails ? "loading…" : "no thumbnail",
                                   thumbnails ? "place " + id : "(this map keeps none: MapConfig.thumbnails)");
  canvas.dataset.thumbnail = thumbnails ? "loading" : "no";
  const frame = el("a", { href: "#/places/" + encodeURIComponent(map) + "/" + id }, canvas);
  const meta = el("div", { class: "meta" });
  const card = el("div", { class: "card ranked-card",
                           dataset: { placeId: String(id), rank: String(rank), score: String(ranked.score || 0),
                                      state: thumbnails ? "loading" : "loaded" } },
                  el("div", {}, el("strong", {}, "#" + rank + " "),
                     el("a", { href: "#/places/" + encodeURIComponent(map) + "/" + id }, "place " + id)),
                  frame,
                  el("div", { class: "meta" }, scoreText, el("br"),
                     "classes: ", classesText(ranked.statistics)),
                  meta);
  const score = el("div", { class: "share-bar" }, el("div", { class: "share" }));
  score.firstChild.style.width = Math.min(100, 100 * Number(ranked.score || 0)) + "%";
  card.insertBefore(score, frame);
  if (!thumbnails) return card;
  placeCalls(() => api("GetPlace", { map, place_id: id, include_thumbnail: true, include_features: true }))
      .then(async (place) => {
        const drawn = await placeCanvas(map, place);
        canvas.replaceWith(drawn);
        const metadata = place.metadata || {};
        meta.replaceChildren(metadata.agent_id || "-", " #", metadata.sequence || 0, " · ",
                             time(metadata.timestamp_ns));
      })
      .catch((e) => {
        canvas.replaceWith(placeholderCanvas(null, "cannot draw", e.message));
      })
      .finally(() => (card.dataset.state = "loaded"));
  return card;
}

async function dynamicsView(view, map, label) {
  view.append(el("h2", {}, "Dynamics of ", el("span", { id: "dynamics-map-name" }, map || "…")));
  if (!map) {
    // No map named: the first available one, its name in the address from here on.
    const list = await api("ListMaps", {});
    const first = (list.maps || []).find((m) => m.available);
    if (!first) {
      view.append(el("p", { class: "muted" }, "No maps yet (placedb maps create NAME)."));
      return;
    }
    map = first.name;
    history.replaceState(null, "", "#/dynamics/" + encodeURIComponent(map));
    view.querySelector("#dynamics-map-name").textContent = map;
  }
  const maps = el("select", { id: "dynamics-map" }, el("option", { value: map }, map));
  const classes = el("select", { id: "dynamics-class" },
                     el("option", { value: "" }, "every class (mean coverage)"));
  const summary = pendingCard("dynamics-summary", "Map totals");
  const classCard = pendingCard("dynamics-class-card", "Classes");
  const hourCard = pendingCard("dynamics-hour-card", "Coverage by hour of day");
  const rankingTitle = el("h3", { id: "dynamics-ranking-title" }, "Places ranked");
  const ranking = el("div", { class: "cards", id: "dynamics-ranking" });
  const more = el("button", { class: "plain", id: "dynamics-next", disabled: "" }, "More");
  view.append(el("div", { class: "bar" }, el("label", {}, "map", maps),
                 el("label", {}, "rank places by", classes)),
              el("div", { class: "cards" }, summary, classCard, hourCard),
              rankingTitle, ranking, el("p", {}, more));

  // Every call at once: the totals (the first cards), the map's settings (does it keep
  // thumbnails?), the other maps for the selector.
  const totals = api("GetDynamics", { map, limit: 1 });
  const description = api("GetMap", { name: map });
  api("ListMaps", {}).then((list) => {
    for (const m of (list.maps || []).filter((m) => m.available && m.name !== map)) {
      maps.append(el("option", { value: m.name }, m.name));
    }
  }, () => {});
  maps.addEventListener("change", () => (location.hash = "#/dynamics/" + encodeURIComponent(maps.value)));

  let measure = null;  // { label: the class's name (null = mean coverage), request }
  let offset = 0;
  let generation = 0;  // a newer ranking drops an older one's late answers
  async function rank(reset) {
    const mine = reset ? ++generation : generation;
    if (reset) {
      offset = 0;
      ranking.replaceChildren(el("p", { class: "muted" }, "Ranking…"));
      ranking.dataset.loaded = "";
    }
    more.disabled = true;
    const [response, settings] = await Promise.all([
      api("GetDynamics", Object.assign({ map, offset, limit: RANKED_PER_PAGE, include_statistics: true },
                                       measure.request)),
      description.catch(() => null),
    ]);
    if (mine !== generation) return;
    if (reset) ranking.replaceChildren();
    const thumbnails = Boolean(settings && settings.config && settings.config.thumbnails &&
                               settings.config.thumbnails.enabled);
    const places = response.places || [];
    const cards = places.map((p, i) => rankedCard(map, p, offset + i + 1, measure, thumbnails));
    ranking.append(...cards);
    if (!ranking.children.length) ranking.append(el("p", { class: "muted" }, "No places ranked."));
    rankingTitle.textContent = "Places ranked by " + (measure.label === null
        ? "mean coverage" : "share of frames with " + measure.label) +
        " (" + Number(response.ranked || 0) + " ranked" + (thumbnails ? "" : "; this map keeps no thumbnails") + ")";
    offset = Number(response.next_offset || 0);
    more.disabled = offset === 0;
    ranking.dataset.loaded = "yes";  // for the browser test: the ranking is shown
  }
  // Ranks by a class id, a class name the map has not seen (the server checks it), or null:
  // mean coverage.
  function choose(classId, name = null) {
    if (classId !== null) {
      measure = { label: className(classId),
                  request: { measure: "DYNAMICS_MEASURE_CLASS_SHARE", class_id: classId } };
    } else if (name) {
      measure = { label: name, request: { measure: "DYNAMICS_MEASURE_CLASS_SHARE", class_name: name } };
    } else {
      measure = { label: null, request: {} };
    }
    classes.value = classId === null ? "" : String(classId);
    history.replaceState(null, "", "#/dynamics/" + encodeURIComponent(map) +
                         (measure.label === null ? "" : "/" + encodeURIComponent(measure.label)));
    return rank(true).catch((e) => {
      showError(e);
      ranking.replaceChildren(el("p", { class: "status" }, (e.code ? e.code + ": " : "") + e.message));
      ranking.dataset.loaded = "error";
    });
  }
  classes.addEventListener("change", () => choose(classes.value === "" ? null : Number(classes.value)));
  more.addEventListener("click", () => rank(false).catch(showError));

  let answer;
  try {
    answer = await totals;
  } catch (e) {
    for (const card of [summary, classCard, hourCard]) card.fail(e);
    throw e;
  }
  const statistics = answer.map || {};
  const seen = [...(statistics.classes || [])].sort((a, b) => Number(b.frames || 0) - Number(a.frames || 0));
  for (const c of seen) classes.append(el("option", { value: String(c.class_id) }, className(c.class_id)));
  summary.fill(totalsTable(statistics, answer.invalid));
  classCard.fill(classesTable(statistics, (id) => choose(id)));
  hourCard.fill(hoursChart(statistics));
  // The class the address names, else the one seen in most frames, else mean coverage.
  const named = label ? seen.find((c) => className(c.class_id) === label) : null;
  if (named) await choose(named.class_id);
  else if (label) await choose(null, label);
  else await choose(seen.length ? seen[0].class_id : null);
}

// ---- Routing ------------------------------------------------------------------------------------

async function route() {
  if (refreshTimer) clearTimeout(refreshTimer);
  refreshTimer = null;
  liveGeneration++;  // a live refresh in flight schedules no next one
  clearStatus();
  const hash = location.hash || "#/maps";
  const view = document.getElementById("view");
  view.replaceChildren();
  view.dataset.ready = "";
  for (const link of document.querySelectorAll("nav a")) {
    link.classList.toggle("active", hash.startsWith(link.getAttribute("href")));
  }
  try {
    if (hash.startsWith("#/places/")) {
      const [map, from] = hash.slice("#/places/".length).split("/");
      await placesView(view, decodeURIComponent(map), Number(from) || 0);
    } else if (hash.startsWith("#/dynamics")) {
      const [map, label] = hash.slice("#/dynamics/".length).split("/");
      await dynamicsView(view, decodeURIComponent(map || ""), decodeURIComponent(label || ""));
    } else if (hash.startsWith("#/query")) {
      await queryView(view);
    } else if (hash.startsWith("#/live")) {
      await liveView(view);
    } else {
      await mapsView(view);
    }
  } catch (error) {
    showError(error);
  }
  view.dataset.ready = "yes";  // for the browser test: the view finished loading
}

async function start() {
  const token = document.getElementById("token");
  token.value = sessionStorage.getItem(TOKEN_KEY) || "";
  token.addEventListener("change", () => {
    if (token.value) sessionStorage.setItem(TOKEN_KEY, token.value.trim());
    else sessionStorage.removeItem(TOKEN_KEY);
    route();
  });
  api("GetServerInfo", {}).then(
      (info) => (document.getElementById("server-version").textContent = "server " + info.version),
      () => {});
  // Both at once; unnamed values show as the API prints them and the views still work.
  const table = (path) => fetch(path).then((r) => (r.ok ? r.json() : {})).catch(() => ({}));
  [enumNames, enumNumbers] = await Promise.all([table("/enum-names.json"),
                                                table("/enum-numbers.json")]);
  window.addEventListener("hashchange", route);
  route();
}

start();
