// pihim live: receives frame packets over a WebSocket and shows S0 / DoLP / AoP with the readouts.
// Packet: uint32 LE header length n, n bytes JSON header, then the JPEG images listed in header.images.
"use strict";
(function () {
  const token = new URLSearchParams(location.search).get("token");
  const $ = (id) => document.getElementById(id);
  const names = ["s0", "dolp", "aop"];
  const urls = {};
  let frames = 0, ws = null, lastHeader = null, lastStatus = null;

  function wsUrl() {
    const u = new URL("ws", location.href);
    u.protocol = location.protocol === "https:" ? "wss:" : "ws:";
    u.search = token ? "?token=" + encodeURIComponent(token) : "";
    return u.toString();
  }
  function fmt(x, digits, unit) { return x === null || x === undefined ? "-" : x.toFixed(digits) + (unit || ""); }
  function setClass(el, cls) { el.classList.remove("good", "warn", "bad"); if (cls) el.classList.add(cls); }

  function showError(status) {
    const el = $("error");
    const now = Date.now() / 1000;
    if (status.error) {
      el.textContent = status.error; el.className = "banner";
    } else if (status.last_error && now - status.last_error.time_unix < 30) {
      const ago = Math.round(now - status.last_error.time_unix);
      el.textContent = "last error (" + ago + " s ago): " + status.last_error.message; el.className = "banner old";
    } else {
      el.className = "banner hidden";
    }
  }

  function drawOverlay(header) {
    const on = $("show-overlay").checked && header.overlay && header.overlay.outlines.length;
    for (const n of names) {
      const img = $("img-" + n), cv = $("ov-" + n);
      const w = img.clientWidth, h = img.clientHeight;
      if (cv.width !== w || cv.height !== h) { cv.width = w; cv.height = h; }
      const g = cv.getContext("2d");
      g.clearRect(0, 0, w, h);
      if (!on) continue;
      g.lineWidth = 1.5; g.strokeStyle = n === "s0" ? "#ff4fd8" : "#ffffff"; g.font = "11px sans-serif";
      g.fillStyle = g.strokeStyle;
      for (const o of header.overlay.outlines) {
        g.beginPath();
        o.points.forEach((p, i) => (i ? g.lineTo(p[0] * w, p[1] * h) : g.moveTo(p[0] * w, p[1] * h)));
        g.closePath(); g.stroke();
        // label at the highest outline point inside the image (or the clamped centroid if none is)
        const inside = o.points.filter((p) => p[0] >= 0 && p[0] <= 1 && p[1] >= 0 && p[1] <= 1);
        let at;
        if (inside.length) at = inside.reduce((a, b) => (b[1] < a[1] ? b : a));
        else {
          const cx = o.points.reduce((s, p) => s + p[0], 0) / o.points.length;
          const cy = o.points.reduce((s, p) => s + p[1], 0) / o.points.length;
          at = [Math.min(Math.max(cx, 0.02), 0.9), Math.min(Math.max(cy, 0.02), 0.95)];
        }
        g.fillText(o.name, Math.min(at[0] * w + 3, w - 30), Math.min(at[1] * h + 12, h - 4));
      }
    }
  }

  function onPacket(buf) {
    const dv = new DataView(buf);
    const n = dv.getUint32(0, true);
    const header = JSON.parse(new TextDecoder().decode(new Uint8Array(buf, 4, n)));
    let pos = 4 + n;
    for (const item of header.images) {
      const blob = new Blob([new Uint8Array(buf, pos, item.bytes)], { type: item.mime });
      pos += item.bytes;
      const img = $("img-" + item.name);
      const old = urls[item.name];
      urls[item.name] = URL.createObjectURL(blob);
      img.src = urls[item.name];
      if (old) setTimeout(() => URL.revokeObjectURL(old), 2000);
    }
    frames += 1; lastHeader = header;
    document.body.dataset.frames = String(frames);
    document.body.dataset.seq = String(header.seq);
    $("frames").textContent = String(frames);
    const src = header.source || {};
    const what = src.view ? "view " + src.view : src.file ? src.file : src.serial ? "camera " + src.serial : "";
    $("frame-src").textContent = what ? "\u00b7 " + what : "";
    $("fps").textContent = fmt(header.fps, 1, " fps");
    const e = header.exposure;
    $("exposure").textContent = e ? fmt(e.exposure_us, 0, " \u00b5s") : "-";
    $("gain").textContent = e ? fmt(e.gain_db, 1, " dB") : "-";
    const c = header.controller;
    $("controller").textContent = c ? (c.applies ? c.reason : c.reason + " (advice \u00d7" + fmt(c.scale, 2) + ")") : "off";
    const rs = header.region_stats;
    const satEl = $("saturated");
    const where = { source: "mirrors", outlines: "in outlines", frame: "whole frame" }[header.region] || header.region;
    satEl.textContent = fmt(100 * rs.fraction_saturated, 2, " %") + " (" + where + ")";
    setClass(satEl, rs.fraction_saturated > 0.001 ? "bad" : "good");
    const dEl = $("dolp");
    // no finite DoLP in the region: every pixel saturated (a brightness step the exposure has not caught up with yet)
    const dolpWhy = header.dolp_mirrors === null && rs.fraction_saturated > 0 ? " (saturated)" : "";
    dEl.textContent = fmt(header.dolp_mirrors, 2) + dolpWhy + (header.region === "frame" ? " (whole frame)" : "");
    setClass(dEl, header.dolp_usable === null ? null : header.dolp_usable ? "good" : "warn");
    showError(header);
    $("capture").disabled = false;
    requestAnimationFrame(() => drawOverlay(header));
  }

  function onStatus(s) {
    lastStatus = s;
    const src = s.source || {};
    $("source").textContent = (src.name || src.kind || "") + (src.width ? " \u2014 " + src.width + "\u00d7" + src.height : "");
    const l = s.latency_ms || {};
    $("latency").textContent = l.p50 === null || l.p50 === undefined ? "-" : fmt(l.p50, 0) + " / " + fmt(l.p95, 0) + " ms";
    showError(s);
  }

  function connect() {
    ws = new WebSocket(wsUrl());
    ws.binaryType = "arraybuffer";
    ws.onopen = () => { $("conn").textContent = "live"; $("conn").className = "pill on"; };
    ws.onmessage = (ev) => {
      if (typeof ev.data === "string") { const m = JSON.parse(ev.data); if (m.type === "status") onStatus(m); }
      else onPacket(ev.data);
    };
    ws.onclose = () => {
      $("conn").textContent = "offline"; $("conn").className = "pill off";
      setTimeout(connect, 1000);
    };
  }

  $("capture").addEventListener("click", async () => {
    const btn = $("capture"), out = $("capture-result");
    const label = $("label").value.trim();
    btn.disabled = true; out.className = "muted"; out.textContent = "writing\u2026";
    const headers = { "Content-Type": "application/json" };
    if (token) headers["Authorization"] = "Bearer " + token;
    try {
      const r = await fetch("api/capture", { method: "POST", headers, body: JSON.stringify(label ? { label } : {}) });
      const body = await r.json();
      if (!r.ok) throw new Error(body.error || r.statusText);
      out.className = "ok";
      out.textContent = "saved " + body.raw_file + " + " + body.json_file + " (" + (body.raw_bytes / 1e6).toFixed(1) + " MB)";
      document.body.dataset.lastCapture = body.raw_file;
    } catch (err) {
      out.className = "bad"; out.textContent = "capture failed: " + err.message;
    } finally { btn.disabled = false; }
  });
  $("show-overlay").addEventListener("change", () => lastHeader && drawOverlay(lastHeader));
  window.addEventListener("resize", () => lastHeader && drawOverlay(lastHeader));
  connect();
})();
