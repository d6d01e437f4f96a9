// ballbot-vision viewer page. One WebSocket; each binary message is one update:
// u32 (big-endian) JSON length, the JSON, then the images named in json.blobs (see services/viewer/core.py).
// The page acks every update once drawn, so the server only ever sends the newest one.
"use strict";

const ORANGE = "#ff8c00", GREEN = "#3ee66b";
const MAX_LABELS = 20; // beyond this many obstacles only the nearest are labelled (all are boxed)
const STAGE_COLOURS = {capture: "#7fb3ff", rectify: "#9be37b", disparity: "#ffd166", segmenter: "#ff9f7f"};
// What this page drew last, for people debugging and for the browser test (tests/test_viewer.py).
const state = window.viewer = {updates: 0, imageUpdates: 0, drawn: null, doc: null, connected: false, errors: []};
const $ = (id) => document.getElementById(id);
let socket = null, updateTimes = [];

function unpack(buffer) {
  const view = new DataView(buffer);
  const n = view.getUint32(0);
  const doc = JSON.parse(new TextDecoder().decode(new Uint8Array(buffer, 4, n)));
  const blobs = {};
  let pos = 4 + n;
  for (const b of doc.blobs) {
    blobs[b.name] = new Blob([new Uint8Array(buffer, pos, b.size)], {type: b.type});
    pos += b.size;
  }
  return {doc, blobs};
}

function paint(canvas, bitmap) {
  canvas.parentElement.classList.toggle("panorama", bitmap.width > 2 * bitmap.height);
  if (canvas.width !== bitmap.width || canvas.height !== bitmap.height) {
    canvas.width = bitmap.width;
    canvas.height = bitmap.height;
  }
  const ctx = canvas.getContext("2d");
  ctx.drawImage(bitmap, 0, 0);
  return ctx;
}

function label(ctx, text, x, y, colour, px) {
  ctx.font = `${px}px "DejaVu Sans", sans-serif`;
  const w = ctx.measureText(text).width + 6;
  const top = Math.max(0, y - px - 4);
  ctx.fillStyle = colour;
  ctx.fillRect(x, top, w, px + 4);
  ctx.fillStyle = "#000";
  ctx.fillText(text, x + 3, top + px);
}

function drawBoxes(ctx, doc) {
  // line and font size grow with the picture, but not past its height (a car's 1344x372)
  const scale = Math.max(1, Math.min(ctx.canvas.width / 640, ctx.canvas.height / 480));
  const drawn = {seq: null, stamp_ns: null, boxes: [], truth: []};
  if (doc.truth) {
    ctx.setLineDash([6 * scale, 4 * scale]);
    ctx.lineWidth = 2 * scale;
    ctx.strokeStyle = GREEN;
    for (const t of doc.truth) {
      const [x0, y0, x1, y1] = t.bbox_px;
      ctx.strokeRect(x0, y0, x1 - x0, y1 - y0);
      drawn.truth.push({name: t.name, bbox_px: [x0, y0, x1, y1]});
    }
    ctx.setLineDash([]);
  }
  const obs = doc.obstacles;
  // boxes only on the picture they were found in (the viewer pairs them by capture stamp)
  if (obs && doc.image && doc.image.matched) {
    drawn.seq = obs.seq;
    drawn.stamp_ns = obs.stamp_ns;
    ctx.lineWidth = 2 * scale;
    ctx.strokeStyle = ORANGE;
    obs.list.forEach((o, i) => { // nearest first
      const [x0, y0, x1, y1] = o.bbox_px;
      // a track not yet confirmed (seen in too few of the last frames) is drawn dashed, as `--draw` does
      ctx.setLineDash(o.confirmed ? [] : [5 * scale, 3 * scale]);
      ctx.strokeRect(x0, y0, x1 - x0, y1 - y0);
      const text = `#${o.id} ${o.distance_m.toFixed(2)} m`;
      if (i < MAX_LABELS) label(ctx, text, x0, y0, ORANGE, 13 * scale);
      drawn.boxes.push({id: o.id, bbox_px: [x0, y0, x1, y1], text, labelled: i < MAX_LABELS,
                        confirmed: o.confirmed});
    });
    ctx.setLineDash([]);
  }
  return drawn;
}

function niceRange(r) {
  for (const step of [2, 3, 4, 5, 6, 8, 10, 15, 20, 30, 40, 60]) if (r <= step) return step;
  return 60;
}

function drawMap(doc, freespaceBitmap) {
  const canvas = $("map"), ctx = canvas.getContext("2d");
  const W = canvas.width, H = canvas.height;
  ctx.fillStyle = "#101316";
  ctx.fillRect(0, 0, W, H);
  const list = doc.obstacles ? doc.obstacles.list : [];
  const base = list.length > 0 ? list.every((o) => o.position_base_m) : !!doc.freespace;
  // (forward, left) of each obstacle in metres, and its footprint (lateral, depth)
  const items = list.map((o) => {
    const p = base && o.position_base_m ? o.position_base_m : null;
    const fwd = p ? p[0] : o.position_m[2], left = p ? p[1] : -o.position_m[0];
    return {o, fwd, left, wide: o.size_m[0], deep: o.size_m[2]};
  });
  let far = 4;
  for (const it of items) far = Math.max(far, (it.fwd + it.deep / 2) * 1.1, Math.abs(it.left) * 2.2);
  if (base && doc.freespace) far = Math.max(far, doc.freespace.top_left_m[0]);
  const range = niceRange(far);
  const scale = (H - 30) / range, u0 = W / 2, v0 = H - 18;
  const at = (fwd, left) => [u0 - left * scale, v0 - fwd * scale];
  if (base && doc.freespace && freespaceBitmap) {
    const fs = doc.freespace;
    const [u, v] = at(fs.top_left_m[0], fs.top_left_m[1]);
    ctx.imageSmoothingEnabled = false;
    ctx.drawImage(freespaceBitmap, u, v, fs.height * fs.resolution_m * scale, fs.width * fs.resolution_m * scale);
  }
  // range rings every metre (or more), and the field of view
  const ring = range <= 10 ? 1 : 5;
  ctx.strokeStyle = "#2e353d";
  ctx.fillStyle = "#77808a";
  ctx.font = "11px sans-serif";
  for (let r = ring; r <= range; r += ring) {
    ctx.beginPath();
    ctx.arc(u0, v0, r * scale, Math.PI, 2 * Math.PI);
    ctx.stroke();
    ctx.fillText(`${r} m`, u0 + 3, v0 - r * scale + 12);
  }
  if (doc.disparity && doc.image) {
    const half = Math.atan2(doc.image.width / 2, doc.disparity.focal_px);
    ctx.strokeStyle = "#56606b";
    ctx.beginPath();
    ctx.moveTo(u0 - Math.sin(half) * range * 2 * scale, v0 - Math.cos(half) * range * 2 * scale);
    ctx.lineTo(u0, v0);
    ctx.lineTo(u0 + Math.sin(half) * range * 2 * scale, v0 - Math.cos(half) * range * 2 * scale);
    ctx.stroke();
  }
  ctx.fillStyle = "#cfd6dd";
  ctx.beginPath();
  ctx.moveTo(u0, v0 - 9);
  ctx.lineTo(u0 - 7, v0 + 6);
  ctx.lineTo(u0 + 7, v0 + 6);
  ctx.fill();
  const stale = doc.obstacles && doc.obstacles.stale;
  items.forEach((it, i) => {
    const [u, v] = at(it.fwd + it.deep / 2, it.left + it.wide / 2);
    ctx.fillStyle = stale ? "rgba(150,150,150,0.5)" : "rgba(255,140,0,0.55)";
    ctx.strokeStyle = ORANGE;
    ctx.fillRect(u, v, Math.max(2, it.wide * scale), Math.max(2, it.deep * scale));
    ctx.strokeRect(u, v, Math.max(2, it.wide * scale), Math.max(2, it.deep * scale));
    ctx.fillStyle = "#fff";
    if (i < MAX_LABELS) ctx.fillText(`#${it.o.id} ${it.o.distance_m.toFixed(2)} m`, u + Math.max(2, it.wide * scale) + 3, v + 10);
  });
  $("map-info").textContent = `(${base ? "robot base: forward up, left left" : "camera: forward up, right right"}` +
    `${base && doc.freespace ? "; green free, red occupied" : ""}; ${range} m)`;
}

function fmt(v, d = 2) { return v === null || v === undefined ? "-" : Number(v).toFixed(d); }

function fillTable(tbody, rows) {
  tbody.replaceChildren(...rows.map((cells) => {
    const tr = document.createElement("tr");
    for (const c of cells) {
      const td = document.createElement("td");
      td.textContent = c;
      tr.appendChild(td);
    }
    return tr;
  }));
}

function drawInfo(doc) {
  $("robot").textContent = doc.robot_id;
  const obs = doc.obstacles;
  $("seq").textContent = obs ? obs.seq : (doc.image ? doc.image.seq : "-");
  $("stale").hidden = !(obs && obs.stale);
  // an empty list of a degraded one is no clear way: say so where the eye is, with the reasons
  const reasons = (obs && obs.degraded) || [];
  $("degraded").hidden = reasons.length === 0;
  $("degraded-reasons").textContent = reasons.join(", ");
  if (obs) {
    const looked = (obs.range_m ? `, looked at ${fmt(obs.range_m[0], 1)}-${fmt(obs.range_m[1], 1)} m` : "") +
      (obs.bearing_deg ? `, ${fmt(obs.bearing_deg[0], 0)} to ${fmt(obs.bearing_deg[1], 0)} deg` : "");
    $("obstacle-count").textContent = `(${obs.list.length}${looked}, nearest first${obs.list.length > MAX_LABELS ? `; the ${MAX_LABELS} nearest labelled on the pictures` : ""})`;
    $("latency").textContent = fmt(obs.latency.capture_to_obstacles_ms, 1);
    fillTable($("obstacles").tBodies[0], obs.list.map((o) => {
      const p = o.position_base_m;
      const fwd = p ? p[0] : o.position_m[2], left = p ? p[1] : -o.position_m[0];
      return [o.id, fmt(o.distance_m), fmt(fwd), fmt(left), o.size_m.map((v) => fmt(v)).join("×"),
              fmt(Math.hypot(...o.velocity_mps)), fmt(o.confidence)];
    }));
    const stages = $("stages"), total = Math.max(1, obs.latency.capture_to_obstacles_ms);
    stages.replaceChildren(...Object.entries(obs.latency.step_ms).map(([name, ms]) => {
      const div = document.createElement("div");
      div.style.width = `${Math.max(0, (100 * ms) / total)}%`;
      div.style.background = STAGE_COLOURS[name] || "#ccc";
      div.textContent = `${name} ${fmt(ms, 1)}`;
      div.title = `${name}: ${fmt(ms, 1)} ms`;
      return div;
    }));
  }
  if (doc.disparity) {
    $("disp-info").textContent = `(${doc.disparity.method}, ${doc.disparity.num_disparities} px searched; near = warm, black = no match)`;
  }
  const services = doc.services || [];
  fillTable($("services").tBodies[0], services.map((s) => [s.service, s.instance, fmt(s.rate_hz, 1), fmt(s.proc_ms, 1),
    fmt(s.age_ms, 1), s.drops, s.errors, s.status]));
  const replay = services.find((s) => s.replay);
  $("replay").hidden = !(replay && doc.viewer && doc.viewer.controls);
  if (replay) {
    const r = replay.replay;
    $("replay-info").textContent = `(${r.paused ? "paused" : "playing"} ${r.index}/${r.total}, x${r.speed})`;
  }
}

async function render(doc, blobs) {
  // Every picture is decoded first and then all is drawn in one go, and window.viewer changes with it:
  // a reader between the awaits (a test, the console, the screen) never sees this update's picture
  // with the last update's boxes, or this update's boxes beside the last update's document.
  // A bitmap holds decoded pixels outside the JavaScript heap until closed: each is closed whatever
  // happens, also when another picture of the update would not decode or drawing throws.
  const decode = (blob) => (blob ? createImageBitmap(blob) : null);
  const settled = await Promise.allSettled([decode(blobs.left), decode(blobs.disparity), decode(blobs.freespace)]);
  const [left, disparity, fs] = settled.map((r) => (r.status === "fulfilled" ? r.value : null));
  let drawn = null;
  try {
    const broken = settled.find((r) => r.status === "rejected");
    if (broken) throw broken.reason;
    if (left) drawn = drawBoxes(paint($("image"), left), doc);
    if (disparity) paint($("disparity"), disparity);
    drawMap(doc, fs);
  } finally {
    for (const bitmap of [left, disparity, fs]) if (bitmap) bitmap.close();
  }
  drawInfo(doc);
  const stamp = doc.obstacles && doc.image && doc.image.matched ? doc.obstacles.stamp_ns : (doc.image ? doc.image.stamp_ns : null);
  if (stamp !== null) {
    state.lastAgeMs = Date.now() - stamp / 1e6; // capture to screen (same clock on one machine)
    $("age").textContent = fmt(state.lastAgeMs, 0);
  }
  const now = performance.now();
  updateTimes.push(now);
  updateTimes = updateTimes.filter((t) => now - t < 2000);
  $("fps").textContent = fmt(updateTimes.length / 2, 1);
  if (drawn) {
    state.drawn = drawn;
    state.imageUpdates += 1;
  }
  state.doc = doc;
  state.updates += 1;
}

// The viewer's token (required when it listens beyond loopback) comes in the page's own URL, as
// printed at start: /?token=...; the WebSocket carries it on.
const token = new URLSearchParams(location.search).get("token") || "";

function connect() {
  const query = token ? `?token=${encodeURIComponent(token)}` : "";
  const ws = new WebSocket(`${location.protocol === "https:" ? "wss" : "ws"}://${location.host}/ws${query}`);
  ws.binaryType = "arraybuffer";
  socket = ws;
  ws.onopen = () => {
    state.connected = true;
    $("conn").textContent = "live";
    $("conn").className = "good";
  };
  ws.onmessage = async (ev) => {
    if (typeof ev.data === "string") {
      const msg = JSON.parse(ev.data);
      if (msg.error) $("message").textContent = msg.error;
      return;
    }
    try {
      const {doc, blobs} = unpack(ev.data);
      await render(doc, blobs);
    } catch (e) {
      state.errors.push(String(e));
      $("message").textContent = `could not draw an update: ${e}`;
    } finally {
      if (ws.readyState === WebSocket.OPEN) ws.send('{"ack":1}');
    }
  };
  ws.onclose = () => {
    state.connected = false;
    $("conn").textContent = "disconnected, retrying";
    $("conn").className = "bad";
    setTimeout(connect, 1000);
  };
}

for (const action of ["play", "pause", "step"]) {
  $(action).onclick = () => socket && socket.readyState === WebSocket.OPEN && socket.send(JSON.stringify({replay: action}));
}
connect();
