// lightplane live: the page.  Plain JavaScript, no library, nothing loaded from elsewhere.
"use strict";

// What the page has seen (read by the browser test and handy in the console).
const lp = window.lpState = {previews: 0, profiles: 0, statuses: 0, lastProfileFrame: null, lastPreviewFrame: null, stripePoints: 0, targets: 0,
  units: null, settings: null, cloudPoints: 0, scan: null, errors: [], guide: null,
  ghostsDrawn: 0, guideAccepted: 0};

const $ = (id) => document.getElementById(id);

async function api(method, path, body) {
  const init = {method, headers: {}};
  if (body !== undefined) {
    init.headers["Content-Type"] = "application/json";
    init.body = JSON.stringify(body);
  }
  const r = await fetch(path, init);
  let data = null;
  try { data = await r.json(); } catch (e) { data = null; }
  if (!r.ok) throw new Error((data && data.error) || `${method} ${path}: HTTP ${r.status}`);
  return data;
}

function say(id, text, ok) {
  const el = $(id);
  el.textContent = text || "";
  el.className = "msg " + (text ? (ok ? "ok" : "error") : "");
  if (text && !ok) lp.errors.push(text);
}

function fmt(v, digits) {
  return (v === null || v === undefined || Number.isNaN(v)) ? "–" : Number(v).toFixed(digits);
}

// ------------------------------------------------------------------ status
function showStatus(s) {
  lp.statuses += 1;
  lp.units = s.units || lp.units;
  $("source").textContent = `${s.source || ""}${s.sensor ? " · sensor " + s.sensor : ""} · profile in ${s.units}`;
  $("fps").textContent = fmt(s.fps, 1);
  const lat = s.latency_ms || {};
  $("lat-med").textContent = fmt(lat.median, 1);
  $("lat-p99").textContent = fmt(lat.p99, 1);
  $("points").textContent = s.points === undefined ? "–" : String(s.points);
  $("dropped").textContent = s.dropped === undefined ? "–" : String(s.dropped);
  $("frames").textContent = s.frames === undefined ? "–" : String(s.frames);
  $("dropped").style.color = s.dropped > 0 ? "var(--warn)" : "";
  $("loop-msg").textContent = s.error ? `live loop: ${s.error}` : (s.ended ? "the source has ended" : "");
  showHardware(s.hardware);
  showRecording(s.recording);
  if (s.scan) showScan(s.scan);
}

// ------------------------------------------------------------------ the live image
const image = {canvas: $("image"), busy: false, img: new Image()};

function stripePairs(uv) {
  if (!uv) return [];
  if (Array.isArray(uv)) {
    if (uv.length && Array.isArray(uv[0])) return uv;
    const out = [];
    for (let i = 0; i + 1 < uv.length; i += 2) out.push([uv[i], uv[i + 1]]);
    return out;
  }
  if (uv.u && uv.v) return uv.u.map((u, i) => [u, uv.v[i]]);
  return [];
}

function drawTarget(ctx, t, s) {
  if (!t) return;
  if (Array.isArray(t)) { t.forEach((x) => drawTarget(ctx, x, s)); return; }
  ctx.strokeStyle = "#ff8c00";
  ctx.fillStyle = "#ff8c00";
  ctx.lineWidth = 2;
  const c = t.center || t.centre || (t.cx !== undefined ? [t.cx, t.cy] : null);
  const axes = t.axes || (t.a !== undefined ? [t.a, t.b] : null);
  if (c && axes) {
    const ang = (t.angle_deg !== undefined ? t.angle_deg : (t.angle || 0)) * Math.PI / 180;
    ctx.beginPath();
    ctx.ellipse(c[0] * s, c[1] * s, Math.abs(axes[0]) * s, Math.abs(axes[1]) * s, ang, 0, 2 * Math.PI);
    ctx.stroke();
    lp.targets += 1;
  }
  if (c) {
    ctx.beginPath();
    ctx.moveTo(c[0] * s - 6, c[1] * s); ctx.lineTo(c[0] * s + 6, c[1] * s);
    ctx.moveTo(c[0] * s, c[1] * s - 6); ctx.lineTo(c[0] * s, c[1] * s + 6);
    ctx.stroke();
  }
  const pts = t.points || t.corners || t.ellipses;
  if (Array.isArray(pts)) {
    for (const p of pts) {
      if (Array.isArray(p)) ctx.fillRect(p[0] * s - 2, p[1] * s - 2, 4, 4);
      else drawTarget(ctx, p, s);
    }
  }
  if (t.label || t.kind) {
    ctx.font = "14px sans-serif";
    ctx.fillText(t.label || t.kind, 6, image.canvas.height - 8);
  }
}

function drawPreview(p) {
  const cv = image.canvas;
  const img = image.img;
  if (cv.width !== img.naturalWidth || cv.height !== img.naturalHeight) {
    cv.width = img.naturalWidth; cv.height = img.naturalHeight;
  }
  const ctx = cv.getContext("2d");
  ctx.drawImage(img, 0, 0);
  const s = p.scale || 1;
  ctx.fillStyle = "#00e04b";
  const uv = stripePairs(p.stripe_uv);
  ctx.beginPath();
  for (const [u, v] of uv) ctx.rect(u - 1, v - 1, 2.5, 2.5);  // already in preview px
  ctx.fill();
  drawTarget(ctx, p.target, 1);  // in preview px, as the stripe centres
  drawGhost(ctx, s);  // the guide's outline is in image px
  lp.previews += 1;
  lp.stripePoints = uv.length;
  lp.lastPreviewFrame = p.frame === undefined ? null : p.frame;
  $("image-info").textContent = `${img.naturalWidth} × ${img.naturalHeight} px shown (scale ${fmt(s, 3)})` +
    `${p.frame !== undefined ? " · frame " + p.frame : ""} · ${uv.length} stripe centres`;
}

async function previewLoop() {
  const width = Math.max(160, Math.min(1280, Math.round(image.canvas.clientWidth * (window.devicePixelRatio || 1))));
  try {
    const p = await api("GET", `api/preview?max_width=${width}`);
    await new Promise((resolve, reject) => {
      image.img.onload = resolve;
      image.img.onerror = () => reject(new Error("the preview image did not decode"));
      image.img.src = "data:image/jpeg;base64," + p.jpeg_base64;
    });
    drawPreview(p);
    setTimeout(previewLoop, 120);
  } catch (e) {
    $("image-info").textContent = e.message;
    setTimeout(previewLoop, 500);
  }
}

// ------------------------------------------------------------------ the profile plot
const plot = {canvas: $("profile"), range: null};

function niceStep(span, n) {
  const raw = span / Math.max(n, 1);
  const mag = Math.pow(10, Math.floor(Math.log10(raw)));
  const r = raw / mag;
  return (r < 1.5 ? 1 : r < 3 ? 2 : r < 7 ? 5 : 10) * mag;
}

function extent(a) {
  let lo = Infinity, hi = -Infinity;
  for (const v of a) { if (v !== null && v < lo) lo = v; if (v !== null && v > hi) hi = v; }
  return [lo, hi];
}

function settleRange(old, lo, hi) {
  // grow at once, shrink over a few frames: the axes do not jump with every frame
  if (!old || !Number.isFinite(old[0])) return [lo, hi];
  const nlo = lo < old[0] ? lo : old[0] + 0.25 * (lo - old[0]);
  const nhi = hi > old[1] ? hi : old[1] - 0.25 * (old[1] - hi);
  return [nlo, nhi];
}

function drawProfile(p) {
  lp.profiles += 1;
  lp.lastProfileFrame = p.frame;
  const mm = p.units === "mm" || (p.x !== undefined && p.u === undefined);
  const xs = mm ? p.x : p.u, ys = mm ? p.z : p.v;
  const unit = mm ? "mm" : "px";
  const xl = mm ? "x" : "u", yl = mm ? "z" : "v";
  $("profile-units").textContent = mm ? "in mm (in the light plane: x along the line, z away from the camera)" : "in px (no sensor file: image coordinates)";
  const cv = plot.canvas, ctx = cv.getContext("2d");
  const W = cv.width, H = cv.height, L = 64, R = 14, T = 14, B = 44;
  ctx.clearRect(0, 0, W, H);
  const n = xs ? xs.length : 0;
  let [x0, x1] = n ? extent(xs) : [0, 1];
  let [y0, y1] = n ? extent(ys) : [0, 1];
  if (!Number.isFinite(x0)) { x0 = 0; x1 = 1; y0 = 0; y1 = 1; }
  const pad = (a, b) => { const d = Math.max((b - a) * 0.05, mm ? 0.5 : 2); return [a - d, b + d]; };
  [x0, x1] = pad(x0, x1); [y0, y1] = pad(y0, y1);
  const key = unit;
  if (!plot.range || plot.range.key !== key) plot.range = {key, x: null, y: null};
  plot.range.x = settleRange(plot.range.x, x0, x1);
  plot.range.y = settleRange(plot.range.y, y0, y1);
  [x0, x1] = plot.range.x; [y0, y1] = plot.range.y;
  const flipY = !mm;  // image rows grow downwards
  const X = (v) => L + (v - x0) / (x1 - x0) * (W - L - R);
  const Y = (v) => flipY ? T + (v - y0) / (y1 - y0) * (H - T - B) : H - B - (v - y0) / (y1 - y0) * (H - T - B);
  drawAxes(ctx, {W, H, L, R, T, B, x0, x1, y0, y1, X, Y}, `${xl} (${unit})`, `${yl} (${unit})`);
  ctx.fillStyle = "#1f5fbf";
  ctx.beginPath();  // one path for all points: one fill
  for (let i = 0; i < n; i++) {
    if (xs[i] === null || ys[i] === null) continue;
    ctx.rect(X(xs[i]) - 1, Y(ys[i]) - 1, 2.2, 2.2);
  }
  ctx.fill();
  const sig = p.sigma_mm;
  let sigText = "";
  if (Array.isArray(sig) && sig.length) {
    const s = sig.filter((v) => v !== null).sort((a, b) => a - b);
    if (s.length) sigText = ` · σ median ${fmt(s[s.length >> 1] * 1000, 1)} µm (one point, from the stripe noise and the calibration)`;
  } else if (typeof sig === "number") {
    sigText = ` · σ ${fmt(sig * 1000, 1)} µm`;
  }
  $("profile-info").textContent = `frame ${p.frame} · ${n} points${sigText}`;
}

function drawAxes(ctx, g, xlabel, ylabel) {
  ctx.strokeStyle = "#9aa3b5"; ctx.fillStyle = "#333"; ctx.lineWidth = 1;
  ctx.font = "12px sans-serif";
  ctx.strokeRect(g.L, g.T, g.W - g.L - g.R, g.H - g.T - g.B);
  const sx = niceStep(g.x1 - g.x0, 7), sy = niceStep(g.y1 - g.y0, 6);
  const dec = (s) => Math.max(0, -Math.floor(Math.log10(s) + 1e-9));
  ctx.textAlign = "center"; ctx.textBaseline = "top";
  for (let v = Math.ceil(g.x0 / sx) * sx; v <= g.x1; v += sx) {
    const x = g.X(v);
    ctx.beginPath(); ctx.moveTo(x, g.H - g.B); ctx.lineTo(x, g.H - g.B + 4); ctx.stroke();
    ctx.fillText(v.toFixed(dec(sx)), x, g.H - g.B + 6);
  }
  ctx.textAlign = "right"; ctx.textBaseline = "middle";
  for (let v = Math.ceil(g.y0 / sy) * sy; v <= g.y1; v += sy) {
    const y = g.Y(v);
    ctx.beginPath(); ctx.moveTo(g.L - 4, y); ctx.lineTo(g.L, y); ctx.stroke();
    ctx.fillText(v.toFixed(dec(sy)), g.L - 6, y);
  }
  ctx.textAlign = "center"; ctx.textBaseline = "bottom";
  ctx.fillText(xlabel, (g.L + g.W - g.R) / 2, g.H - 4);
  ctx.save(); ctx.translate(14, (g.T + g.H - g.B) / 2); ctx.rotate(-Math.PI / 2);
  ctx.textBaseline = "middle"; ctx.fillText(ylabel, 0, 0); ctx.restore();
}

// ------------------------------------------------------------------ settings
// settings with a few known values: a list to choose from ("" stands for none)
const CHOICES = {channel: ["", "red", "green", "blue", "gray"], axis: ["auto", "columns", "rows"]};

function settingInput(name, value) {
  let el;
  if (CHOICES[name]) {
    el = document.createElement("select");
    for (const c of CHOICES[name]) {
      const o = document.createElement("option");
      o.value = c; o.textContent = c === "" ? "(image as it is)" : c;
      el.append(o);
    }
    el.value = value === null ? "" : value;
    el.id = "set-" + name; el.name = name; el.dataset.kind = "choice";
    return el;
  }
  if (typeof value === "boolean") {
    el = document.createElement("input"); el.type = "checkbox"; el.checked = value;
  } else if (typeof value === "number") {
    el = document.createElement("input"); el.type = "number"; el.step = "any"; el.value = String(value);
  } else {
    el = document.createElement("input"); el.type = "text";
    el.value = value === null ? "" : (Array.isArray(value) ? value.join(", ") : String(value));
    if (value === null) el.placeholder = "(none)";
  }
  el.id = "set-" + name; el.name = name;
  el.dataset.kind = value === null ? "null" : Array.isArray(value) ? "json" : typeof value;
  return el;
}

function settingValue(el) {
  const kind = el.dataset.kind;
  if (kind === "choice") return el.value === "" ? null : el.value;
  if (kind === "boolean") return el.checked;
  if (kind === "number") return el.value === "" ? null : Number(el.value);
  const text = el.value.trim();
  if (text === "") return null;
  if (kind === "json" || kind === "object") return JSON.parse(text.startsWith("[") ? text : `[${text}]`);
  if (kind === "null") {  // a number, a list (x, y, w, h) or a name
    if (!Number.isNaN(Number(text))) return Number(text);
    if (/^[\[\d]/.test(text)) return JSON.parse(text.startsWith("[") ? text : `[${text}]`);
    return text;
  }
  return el.value;
}

function showSettings(s) {
  lp.settings = s;
  const form = $("settings");
  for (const [name, value] of Object.entries(s)) {
    let el = $("set-" + name);
    if (!el) {
      const label = document.createElement("label");
      label.htmlFor = "set-" + name; label.textContent = name.replaceAll("_", " ");
      el = settingInput(name, value);
      form.append(label, el);
    } else if (document.activeElement !== el) {
      if (el.type === "checkbox") el.checked = !!value;
      else el.value = value === null ? "" : (Array.isArray(value) ? value.join(", ") : String(value));
    }
  }
}

async function changeSetting(ev) {
  const el = ev.target;
  let value;
  try { value = settingValue(el); } catch (e) { say("settings-msg", `${el.name}: not valid JSON`); return; }
  try {
    const s = await api("POST", "api/settings", {[el.name]: value});
    showSettings(s);
    say("settings-msg", `${el.name} = ${JSON.stringify(s[el.name])}`, true);
  } catch (e) {
    say("settings-msg", e.message);
    showSettings(await api("GET", "api/settings"));
  }
}

// ------------------------------------------------------------------ hardware
function showHardware(hw) {
  const box = $("lasers");
  $("tt-go").disabled = !(hw && hw.turntable) || scan.busy;
  if (!hw) {
    box.textContent = "no hardware (start with --hardware)"; $("tt-angle").textContent = "";
    $("stage-row").hidden = true; return;
  }
  if (box.childElementCount !== hw.n_lasers) {
    box.textContent = "";
    for (let i = 0; i < hw.n_lasers; i++) {
      const label = document.createElement("label");
      const cb = document.createElement("input");
      cb.type = "checkbox"; cb.id = "laser-" + i; cb.disabled = scan.busy;
      cb.addEventListener("change", () => setLaser(i, cb.checked));
      label.append(cb, ` laser ${i} `);
      box.append(label);
    }
  }
  hw.lasers.forEach((on, i) => { const cb = $("laser-" + i); if (cb && document.activeElement !== cb) cb.checked = on; });
  $("tt-angle").textContent = hw.turntable ? `turntable at ${fmt(hw.angle_deg, 2)} deg` : "no turntable";
  $("stage-row").hidden = !hw.stage;
  $("st-pos").textContent = hw.stage ? `stage at ${fmt(hw.position_mm, 3)} mm` : "";
}

async function moveStage() {
  const mm = Number($("st-mm").value);
  $("st-go").disabled = true;
  try {
    const r = await api("POST", "api/stage", {mm});
    say("hw-msg", `moved by ${mm} mm, now at ${fmt(r.position_mm, 3)} mm`, true);
  } catch (e) { say("hw-msg", e.message); }
  $("st-go").disabled = false;
}

async function setLaser(i, on) {
  try { await api("POST", "api/laser", {index: i, on}); say("hw-msg", `laser ${i} ${on ? "on" : "off"}`, true); } catch (e) { say("hw-msg", e.message); }
}

async function turn() {
  const deg = Number($("tt-deg").value);
  $("tt-go").disabled = true;
  try {
    const r = await api("POST", "api/turntable", {degrees: deg});
    say("hw-msg", `turned by ${deg} deg, now at ${fmt(r.angle_deg, 2)} deg`, true);
  } catch (e) { say("hw-msg", e.message); }
  $("tt-go").disabled = false;
}

// ------------------------------------------------------------------ record
function showRecording(rec) {
  const on = !!(rec && (rec === true || rec.active || rec.folder));
  $("rec-start").disabled = on; $("rec-stop").disabled = !on;
  if (on) $("rec-state").textContent = `recording${rec.folder ? " into " + rec.folder : ""}` +
    `${rec.frames !== undefined ? " · " + rec.frames + " frames" : ""}`;
}

function listFiles(id, files) {
  const ul = $(id); ul.textContent = "";
  for (const [k, v] of Object.entries(files || {})) {
    const li = document.createElement("li");
    li.textContent = `${k}: ${String(v).split("/").pop()}`; li.title = String(v);
    ul.append(li);
  }
}

async function record(action) {
  try {
    const body = action === "start" ? {action, folder: $("rec-folder").value.trim() || null} : {action};
    const r = await api("POST", "api/record", body);
    if (action === "start") { showRecording({folder: r.folder}); listFiles("rec-files", {}); say("rec-msg", ""); } else {
      showRecording(false); $("rec-state").textContent = "recording written"; listFiles("rec-files", r.files);
      say("rec-msg", `${Object.keys(r.files || {}).length} files written`, true);
    }
  } catch (e) { say("rec-msg", e.message); }
}

// ------------------------------------------------------------------ scan
const scan = {polling: false, next: 0, done: false, busy: false};

function scanRunning(s) {
  return !!s && (s.running === true || s.state === "running" || s.state === "scanning" || s.state === "starting");
}

function showScan(s) {
  lp.scan = s;
  const total = s.steps || s.total || 0, done = s.step !== undefined ? s.step : (s.done || 0);
  $("scan-progress").max = Math.max(total, 1); $("scan-progress").value = Math.min(done, total || 1);
  const parts = [];
  if (s.state) parts.push(s.state);
  if (total) parts.push(`step ${done} of ${total}`);
  if (s.points !== undefined) parts.push(`${s.points} points`);
  if (s.folder) parts.push(String(s.folder));
  $("scan-state").textContent = parts.join(" · ");
  if (s.error) say("scan-msg", s.error);
  if (s.files) listFiles("scan-files", s.files);
  $("scan-start").disabled = scanRunning(s);
  scan.busy = scanRunning(s);  // the scan drives the lasers and the table: their controls wait
  for (const el of document.querySelectorAll("#lasers input, #tt-go, #st-go")) el.disabled = scan.busy;
  if (scanRunning(s) && !scan.polling) pollScan();
}

async function startScan() {
  try {
    const body = {kind: $("scan-kind").value, steps: Math.round(Number($("scan-steps").value)),
      step: Number($("scan-step").value), folder: $("scan-folder").value.trim() || null};
    cloud.reset();
    scan.next = 0;
    listFiles("scan-files", {});
    say("scan-msg", "");
    showScan(await api("POST", "api/scan", body));
    pollScan();
  } catch (e) { say("scan-msg", e.message); }
}

async function pollScan() {
  if (scan.polling) return;
  scan.polling = true;
  try {
    for (;;) {
      const s = await api("GET", "api/scan");
      const pts = await api("GET", `api/scan/points?since=${scan.next}`);
      if (pts.count) { cloud.add(pts.points); scan.next = pts.next; }
      showScan(s);
      if (!scanRunning(s)) break;
      await new Promise((r) => setTimeout(r, 400));
    }
  } catch (e) { say("scan-msg", e.message); }
  scan.polling = false;
}

// ------------------------------------------------------------------ the cloud (software point renderer)
const cloud = {
  canvas: $("cloud"), pts: new Float32Array(3 * 65536), n: 0, lo: [Infinity, Infinity, Infinity],
  hi: [-Infinity, -Infinity, -Infinity], yaw: 0.6, pitch: 0.5, zoom: 1, dirty: true,
  reset() { this.n = 0; this.lo = [Infinity, Infinity, Infinity]; this.hi = [-Infinity, -Infinity, -Infinity]; this.dirty = true; },
  add(flat) {
    const m = Math.floor(flat.length / 3);
    if (3 * (this.n + m) > this.pts.length) {
      const bigger = new Float32Array(Math.max(2 * this.pts.length, 3 * (this.n + m)));
      bigger.set(this.pts.subarray(0, 3 * this.n)); this.pts = bigger;
    }
    for (let i = 0; i < 3 * m; i++) {
      const v = flat[i] === null ? NaN : flat[i];
      this.pts[3 * this.n + i] = v;
      const k = i % 3;
      if (v < this.lo[k]) this.lo[k] = v;
      if (v > this.hi[k]) this.hi[k] = v;
    }
    this.n += m; lp.cloudPoints = this.n; this.dirty = true;
  },
};

function drawCloud() {
  const cv = cloud.canvas, W = cv.width, H = cv.height, ctx = cv.getContext("2d");
  const im = ctx.createImageData(W, H), buf = new Uint32Array(im.data.buffer), depth = new Float32Array(W * H);
  buf.fill(0xffffffff); depth.fill(Infinity);
  const c = [0, 1, 2].map((k) => (cloud.lo[k] + cloud.hi[k]) / 2);
  const span = Math.max(cloud.hi[0] - cloud.lo[0], cloud.hi[1] - cloud.lo[1], cloud.hi[2] - cloud.lo[2], 1e-6);
  const s = 0.8 * Math.min(W, H) / span * cloud.zoom;
  const cy = Math.cos(cloud.yaw), sy = Math.sin(cloud.yaw), cp = Math.cos(cloud.pitch), sp = Math.sin(cloud.pitch);
  const zlo = cloud.lo[2], zspan = Math.max(cloud.hi[2] - cloud.lo[2], 1e-6);
  const P = cloud.pts;
  for (let i = 0; i < cloud.n; i++) {
    const x = P[3 * i] - c[0], y = P[3 * i + 1] - c[1], z = P[3 * i + 2] - c[2];
    if (!(x === x && y === y && z === z)) continue;
    const x1 = cy * x + sy * z, z1 = -sy * x + cy * z;      // turn about the vertical axis
    const y2 = cp * y - sp * z1, z2 = sp * y + cp * z1;       // then tilt
    const u = Math.round(W / 2 + x1 * s), v = Math.round(H / 2 + y2 * s);
    if (u < 0 || v < 0 || u >= W - 1 || v >= H - 1) continue;
    const t = (P[3 * i + 2] - zlo) / zspan, shade = 0.55 + 0.45 * Math.max(-1, Math.min(1, -z2 / span));
    const r = Math.round(shade * (40 + 200 * t)), g = Math.round(shade * (90 + 80 * (1 - Math.abs(2 * t - 1)))),
      b = Math.round(shade * (220 - 180 * t));
    const col = 0xff000000 | (b << 16) | (g << 8) | r;
    for (const o of [0, 1, W, W + 1]) {
      const j = v * W + u + o;
      if (z2 < depth[j]) { depth[j] = z2; buf[j] = col; }
    }
  }
  ctx.putImageData(im, 0, 0);
  drawCloudAxes(ctx, W, H, s, {cy, sy, cp, sp});
  $("cloud-info").textContent = cloud.n ? `${cloud.n} points · extent ${fmt(cloud.hi[0] - cloud.lo[0], 1)} × ` +
    `${fmt(cloud.hi[1] - cloud.lo[1], 1)} × ${fmt(cloud.hi[2] - cloud.lo[2], 1)} mm` : "no points yet: start a scan";
}

function drawCloudAxes(ctx, W, H, s, r) {
  const o = [46, H - 46], L = 30;
  const axes = [["x", [1, 0, 0], "#c0392b"], ["y", [0, 1, 0], "#27ae60"], ["z", [0, 0, 1], "#2962ff"]];
  ctx.lineWidth = 2; ctx.font = "12px sans-serif";
  for (const [name, [x, y, z], col] of axes) {
    const x1 = r.cy * x + r.sy * z, z1 = -r.sy * x + r.cy * z, y2 = r.cp * y - r.sp * z1;
    ctx.strokeStyle = col; ctx.fillStyle = col;
    ctx.beginPath(); ctx.moveTo(o[0], o[1]); ctx.lineTo(o[0] + L * x1, o[1] + L * y2); ctx.stroke();
    ctx.fillText(name, o[0] + (L + 8) * x1 - 3, o[1] + (L + 8) * y2 + 4);
  }
  if (!cloud.n) return;
  const bar = niceStep(0.25 * W / s, 1);  // a scale bar of a round length
  ctx.strokeStyle = "#333"; ctx.fillStyle = "#333";
  ctx.beginPath(); ctx.moveTo(W - 20 - bar * s, H - 20); ctx.lineTo(W - 20, H - 20); ctx.stroke();
  ctx.textAlign = "center"; ctx.fillText(`${bar} mm`, W - 20 - bar * s / 2, H - 26); ctx.textAlign = "start";
}

function cloudMouse() {
  const cv = cloud.canvas;
  let drag = null;
  cv.addEventListener("mousedown", (e) => { drag = [e.clientX, e.clientY]; cv.style.cursor = "grabbing"; });
  window.addEventListener("mouseup", () => { drag = null; cv.style.cursor = "grab"; });
  window.addEventListener("mousemove", (e) => {
    if (!drag) return;
    cloud.yaw += (e.clientX - drag[0]) * 0.01;
    cloud.pitch = Math.max(-1.55, Math.min(1.55, cloud.pitch + (e.clientY - drag[1]) * 0.01));
    drag = [e.clientX, e.clientY]; cloud.dirty = true;
  });
  cv.addEventListener("wheel", (e) => { e.preventDefault(); cloud.zoom *= Math.exp(-e.deltaY * 0.001); cloud.dirty = true; },
    {passive: false});
  cv.addEventListener("dblclick", () => { cloud.yaw = 0.6; cloud.pitch = 0.5; cloud.zoom = 1; cloud.dirty = true; });
}

function frameLoop() {
  if (cloud.dirty) { cloud.dirty = false; drawCloud(); }
  requestAnimationFrame(frameLoop);
}

// ------------------------------------------------------------------ the websocket
function connect() {
  const proto = location.protocol === "https:" ? "wss:" : "ws:";
  const ws = new WebSocket(`${proto}//${location.host}/api/ws`);
  ws.onopen = () => { ws.send(JSON.stringify({profile_hz: 15})); $("conn").textContent = "live"; $("conn").className = "badge ok"; };
  ws.onclose = () => {
    $("conn").textContent = "disconnected"; $("conn").className = "badge bad";
    setTimeout(connect, 1000);
  };
  ws.onmessage = (m) => {
    const ev = JSON.parse(m.data);
    if (ev.type === "profile") drawProfile(ev);
    else if (ev.type === "status") showStatus(ev);
    else if (ev.type === "settings" && ev.settings) showSettings(ev.settings);
    else if (ev.type && ev.type.startsWith("scan")) api("GET", "api/scan").then(showScan).catch(() => {});
  };
}

// ------------------------------------------------------------------ guided calibration
function drawGhost(ctx, s) {
  const g = lp.guide;
  if (!g || !g.active || !g.suggestion) return;
  const pts = g.suggestion.outline_px;
  ctx.save();
  ctx.strokeStyle = "#ff4fd8";
  ctx.lineWidth = 2;
  ctx.setLineDash([8, 6]);
  ctx.beginPath();
  pts.forEach(([u, v], i) => (i ? ctx.lineTo(u * s, v * s) : ctx.moveTo(u * s, v * s)));
  ctx.closePath();
  ctx.stroke();
  ctx.restore();
  lp.ghostsDrawn += 1;
}

function showGuide(g) {
  lp.guide = g;
  $("guide-accept").disabled = !(g && g.active && g.verdict && g.verdict.status === "continue");
  if (!g || !g.active) { $("guide-state").textContent = "not started"; return; }
  $("guide-state").textContent = `${g.n_placements} placements · ${g.figure}: ${fmt(g.sigma_mm, 4)} mm ` +
    `(target ${fmt(g.target_sigma_mm, 4)} mm) · RMS camera frame ${fmt(g.rms_camera_frame_mm, 4)} mm, ` +
    `shape ${fmt(g.rms_shape_mm, 4)} mm`;
  const s = g.suggestion;
  $("guide-next").textContent = s ? `next: the ghost, ${fmt(s.distance_mm, 0)} mm away, tilted ${fmt(s.tilt_deg, 0)} deg; ` +
    `σ after it ${fmt(s.sigma_after_mm, 4)} mm` : "";
  const ol = $("guide-history");
  ol.innerHTML = "";
  for (const v of g.history_sigma_mm) {
    const li = document.createElement("li");
    li.textContent = `σ ${fmt(v, 4)} mm`;
    ol.appendChild(li);
  }
  const st = g.verdict.status;
  say("guide-verdict", st === "continue" ? "" : g.verdict.message, st === "reached");
}

async function guideStart() {
  say("guide-msg", "");
  try {
    showGuide(await api("POST", "api/guide", {target_sigma_mm: Number($("guide-sigma").value),
      diameter_mm: Number($("guide-diameter").value), working_volume: $("guide-volume").value}));
  } catch (e) { say("guide-msg", e.message); }
}

async function guideAccept() {
  say("guide-msg", "");
  $("guide-accept").disabled = true;
  try {
    showGuide(await api("POST", "api/guide/accept", {}));
    lp.guideAccepted += 1;
  } catch (e) { say("guide-msg", e.message); showGuide(lp.guide); }
}

async function guideLoop() {
  try { showGuide(await api("GET", "api/guide")); } catch (e) { /* shown on the next action */ }
  setTimeout(guideLoop, 1000);
}

async function main() {
  $("settings").addEventListener("change", changeSetting);
  $("settings").addEventListener("submit", (e) => e.preventDefault());
  $("tt-go").addEventListener("click", turn);
  $("st-go").addEventListener("click", moveStage);
  $("rec-start").addEventListener("click", () => record("start"));
  $("rec-stop").addEventListener("click", () => record("stop"));
  $("scan-start").addEventListener("click", startScan);
  $("scan-kind").addEventListener("change", () => {
    $("scan-step-unit").textContent = $("scan-kind").value === "turntable" ? "deg" : "mm";
  });
  $("guide-start").addEventListener("click", guideStart);
  $("guide-accept").addEventListener("click", guideAccept);
  cloudMouse();
  requestAnimationFrame(frameLoop);
  try { showSettings(await api("GET", "api/settings")); } catch (e) { say("settings-msg", e.message); }
  try { showStatus(await api("GET", "api/status")); } catch (e) { /* the websocket brings it */ }
  try { showScan(await api("GET", "api/scan")); } catch (e) { /* no scan yet */ }
  connect();
  previewLoop();
  guideLoop();
}

main();
