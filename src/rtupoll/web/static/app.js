// rtupoll dashboard: the state from /api/events (server-sent events), trends from
// /api/trend. No framework, no network beyond this server; plain DOM and SVG.
"use strict";

(function () {
  const app = document.getElementById("app");
  const conn = document.getElementById("conn");
  let state = null; // the last snapshot, updated in place by device events
  let offset = 0; // server time - browser time, seconds
  const open = new Set(); // "KEY\u0000FIELD" of the charts that are open
  const series = new Map(); // same key -> {t: [...], v: [...]}
  const SEP = "\u0000";
  // for benchmarks/web_browser.py: per device event, seconds from the reading to the
  // page updated, and milliseconds the update took (the last PERF of each)
  const PERF = 2000;
  const perf = window.rtupollPerf = { latency: [], update: [], events: 0 };
  window.rtupollModel = function () { return state; }; // the merged model (the tests read it)
  function note(list, v) { list.push(v); if (list.length > PERF) list.shift(); }

  function now() { return Date.now() / 1000 + offset; }

  function el(tag, cls, text) {
    const e = document.createElement(tag);
    if (cls) e.className = cls;
    if (text !== undefined && text !== null) e.textContent = String(text);
    return e;
  }

  function svgEl(tag, attrs) {
    const e = document.createElementNS("http://www.w3.org/2000/svg", tag);
    for (const k in attrs) e.setAttribute(k, String(attrs[k]));
    return e;
  }

  function ago(seconds) {
    if (seconds < 0) seconds = 0;
    if (seconds < 60) return seconds.toFixed(0) + " s";
    if (seconds < 3600) return (seconds / 60).toFixed(0) + " min";
    if (seconds < 86400) return (seconds / 3600).toFixed(1) + " h";
    return (seconds / 86400).toFixed(1) + " d";
  }

  function ms(seconds) { return seconds === null || seconds === undefined ? "—" : (seconds * 1000).toFixed(0) + " ms"; }

  function clock(t) {
    const d = new Date((t - offset) * 1000);
    return d.toLocaleTimeString([], { hour: "2-digit", minute: "2-digit", second: "2-digit", hourCycle: "h23" });
  }

  function badge(name, sev) { return el("span", "badge sev-" + (sev || "info"), name); }

  // -- rendering ----------------------------------------------------------------

  function down(dev) { return dev.state === "retrying" || dev.state === "offline"; }

  function renderAll() {
    app.textContent = "";
    if (!state) return;
    document.getElementById("title").textContent =
      state.mode === "fleet" ? "fleet · " + (state.title || "") : (state.gateways[0] && state.gateways[0].title) || "";
    if (!state.gateways.length) {
      app.appendChild(el("p", "empty", state.mode === "fleet"
        ? "No rtupoll gateway has published to this broker yet (waiting for BASE/bridge/info)."
        : "No devices."));
    }
    for (const gw of state.gateways) app.appendChild(renderGateway(gw));
    drawCharts(app);
    fit(app);
    summary();
  }

  function renderGateway(gw) {
    const sec = el("section", "gateway" + (gw.online ? "" : " down"));
    sec.id = "gw-" + gw.id;
    sec.dataset.gateway = gw.id;
    const h = el("h2");
    h.appendChild(el("span", "gw-name", gw.id));
    if (state.mode === "fleet") {
      h.appendChild(el("span", "badge " + (gw.online ? "st-online" : "st-offline"), gw.online ? "online" : "offline"));
    }
    const meta = [gw.version ? "rtupoll " + gw.version : "", gw.base ? gw.base : ""].filter(Boolean).join(" · ");
    if (meta) h.appendChild(el("span", "meta", meta));
    sec.appendChild(h);
    for (const bus of gw.buses) sec.appendChild(renderBus(gw, bus));
    return sec;
  }

  function renderBus(gw, bus) {
    const sec = el("section", "bus");
    sec.dataset.bus = bus.name;
    const h = el("h3");
    h.appendChild(el("span", "bus-name", bus.name));
    const meta = el("span", "meta bus-meta");
    fillBusMeta(meta, bus);
    h.appendChild(meta);
    sec.appendChild(h);
    const served = el("div", "served");
    fillServed(served, bus.gateway);
    sec.appendChild(served);
    const grid = el("div", "devices");
    for (const dev of bus.devices) grid.appendChild(renderDevice(gw, dev));
    sec.appendChild(grid);
    return sec;
  }

  function fillBusMeta(meta, bus) {
    meta.textContent = "";
    const parts = [bus.port, bus.serial].filter(Boolean).join(" · ");
    if (parts) meta.appendChild(document.createTextNode(parts + " "));
    if (typeof bus.utilisation === "number") {
      const bar = el("span", "load");
      bar.title = "bus busy " + (bus.utilisation * 100).toFixed(0) + " %";
      const fill = el("span");
      fill.style.width = Math.min(100, bus.utilisation * 100).toFixed(1) + "%";
      bar.appendChild(fill);
      meta.appendChild(bar);
      meta.appendChild(document.createTextNode(" " + (bus.utilisation * 100).toFixed(0) + " % busy"));
    }
    if (bus.port_error) meta.appendChild(el("span", "port-error", " · port gone: " + bus.port_error));
  }

  function fillServed(box, g) {
    box.textContent = "";
    box.hidden = !g;
    if (!g) return;
    const connected = g.clients.filter(function (c) { return c.connected; }).length;
    box.appendChild(document.createTextNode("gateway " + g.listen + " · " + connected +
      " connected · " + g.pending + " queued"));
    if (!g.clients.length) return;
    const t = el("table");
    const head = el("tr");
    for (const c of ["client", "requests", "answered", "exceptions", "timeouts", "busy", "refused", "wait p95"]) head.appendChild(el("th", "", c));
    t.appendChild(head);
    for (const c of g.clients) {
      const r = el("tr", c.connected ? "" : "gone");
      for (const v of [c.client, c.requests, c.answered, c.exceptions, c.timeouts, c.busy, c.refused, ms(c.wait_p95)]) r.appendChild(el("td", "", v));
      t.appendChild(r);
    }
    box.appendChild(t);
  }

  function renderDevice(gw, dev) {
    const card = el("article", cardClass(dev));
    card.dataset.key = dev.key;
    card.dataset.state = dev.state;
    card.appendChild(renderHeader(dev));
    card.appendChild(el("div", "model", [dev.model, dev.profile + "@" + dev.address].filter(Boolean).join(" · ")));
    const t = el("table", "fields");
    const body = el("tbody");
    for (const f of dev.fields) {
      const row = renderField(dev, f);
      body.appendChild(row);
      const k = dev.key + SEP + f.name;
      if (open.has(k) && f.kind === "number") {
        row.classList.add("open");
        body.appendChild(chartRow(k, f));
      }
    }
    t.appendChild(body);
    card.appendChild(t);
    card.appendChild(renderHealth(dev));
    return card;
  }

  function cardClass(dev) { return "device st-" + dev.state + (down(dev) ? " down" : ""); }

  function renderHeader(dev) {
    const head = el("header");
    head.appendChild(el("span", "name", dev.name));
    head.appendChild(el("span", "badge state st-" + dev.state, stateText(dev)));
    return head;
  }

  // in place: the rows stay the same elements (focus, a click under way, open charts);
  // only the rows of the fields in `changed` (a Set of names, or null: all) are redrawn
  function updateDevice(card, gw, dev, changed) {
    const rows = card.querySelectorAll("tr.field");
    let same = rows.length === dev.fields.length;
    for (let i = 0; same && i < rows.length; i++) same = rows[i].dataset.field === dev.fields[i].name;
    if (!same) {
      const fresh = renderDevice(gw, dev);
      card.replaceWith(fresh);
      drawCharts(fresh);
      return fresh;
    }
    card.className = cardClass(dev);
    card.dataset.state = dev.state;
    card.replaceChild(renderHeader(dev), card.querySelector("header"));
    for (let i = 0; i < rows.length; i++) {
      if (changed && !changed.has(dev.fields[i].name)) continue;
      const row = rows[i], nr = renderField(dev, dev.fields[i]);
      row.className = nr.className + (row.classList.contains("open") ? " open" : "");
      row.replaceChild(nr.children[1], row.children[1]);
    }
    card.replaceChild(renderHealth(dev), card.querySelector(".health"));
    drawCharts(card);
    return card;
  }

  function stateText(dev) {
    if (down(dev) && dev.health && dev.health.next_try) {
      const wait = dev.health.next_try - now();
      return dev.state + (wait >= 1 ? ", next try in " + wait.toFixed(0) + " s" : ", trying");
    }
    return dev.state;
  }

  function renderField(dev, f) {
    const row = el("tr", "field sev-" + (f.severity || "ok") + (f.kind === "number" ? " num" : ""));
    row.dataset.field = f.name;
    if (f.kind === "number") row.tabIndex = 0;
    const th = el("th", "", f.label || f.name);
    th.title = f.name + (f.description ? ": " + f.description : "");  // the name scripts use
    row.appendChild(th);
    const td = el("td", "val");
    if (f.status === "ok" || f.status === "") {
      if (f.kind === "flags") {
        if (f.badges.length) for (const b of f.badges) td.appendChild(badge(b.name, b.severity));
        else td.appendChild(el("span", "badge none", "none"));
      } else if (f.kind === "enum" || (f.badges.length && f.value === null)) {
        for (const b of f.badges) td.appendChild(badge(b.name, b.severity));
      } else {
        td.appendChild(el("span", "v", f.text));
        if (f.unit && f.text !== "") td.appendChild(el("span", "unit", f.unit));
      }
    } else {
      td.appendChild(el("span", f.status === "absent" || f.status === "waiting" || f.status === "offline" ? "last" : "failed", f.text || f.status));
      if (f.error) td.title = f.error;
      if (f.last) {
        td.appendChild(document.createTextNode(" "));
        td.appendChild(el("span", "last", "(last " + f.last.text + (f.unit ? " " + f.unit : "") + " at " + clock(f.last.time) + ")"));
      }
    }
    row.appendChild(td);
    return row;
  }

  function renderHealth(dev) {
    const h = el("div", "health");
    const x = dev.health || {};
    function item(label, value, bad) {
      const s = el("span", bad ? "bad" : "");
      s.appendChild(document.createTextNode(label + " "));
      s.appendChild(el("b", "", value));
      h.appendChild(s);
    }
    if (typeof x.ok === "number") {
      item("ok", x.ok);
      item("timeouts", x.timeouts, x.timeouts > 0);
      item("garbled", x.garbled, x.garbled > 0);
      item("late", x.late, x.late > 0);
      if (x.exceptions) item("exceptions", x.exceptions, true);
      if (x.timeout !== null && x.timeout !== undefined) item("timeout", ms(x.timeout) + (x.timeout_source ? " " + x.timeout_source : ""));
    }
    const seen = el("span", "seen");
    seen.dataset.seen = x.last_seen === null || x.last_seen === undefined ? "" : String(x.last_seen);
    seen.textContent = seenText(x.last_seen);
    h.appendChild(seen);
    if (dev.error) h.appendChild(el("span", "bad", dev.error));
    return h;
  }

  function seenText(t) {
    if (t === null || t === undefined || t === "") return "never seen";
    return "last seen " + ago(now() - t) + " ago";
  }

  // -- charts ---------------------------------------------------------------------

  function chartRow(k, f) {
    const tr = el("tr", "chart-row");
    tr.dataset.chart = k;
    const td = el("td", "chart");
    td.colSpan = 2;
    tr.appendChild(td);
    return tr; // drawn by drawCharts once in the page (it needs its width)
  }

  function draw(td, k, f) {
    td.textContent = "";
    const s = series.get(k);
    // drawn at the width it is shown at, so its text is not stretched
    const W = Math.max(200, Math.round(td.clientWidth || (td.closest("table") || app).clientWidth || 320));
    const H = 130, L = 46, R = 6, T = 8, B = 18;
    const svg = svgEl("svg", { class: "trend", viewBox: "0 0 " + W + " " + H, role: "img" });
    svg.setAttribute("aria-label", "trend of " + (f.label || f.name));
    const t1 = now();
    const span = state ? state.span : 3600;
    const ts = [], vs = [];
    if (s) {
      for (let i = 0; i < s.t.length; i++) if (s.t[i] >= t1 - span) { ts.push(s.t[i]); vs.push(s.v[i]); }
    }
    svg.dataset.points = String(ts.length);
    if (!ts.length) {
      td.appendChild(svg);
      td.appendChild(el("div", "chart-note", s ? "no readings in the last hour yet" : "loading…"));
      return;
    }
    let lo = Math.min.apply(null, vs), hi = Math.max.apply(null, vs);
    if (lo === hi) { lo -= Math.abs(lo) * 0.05 || 1; hi += Math.abs(hi) * 0.05 || 1; }
    const pad = (hi - lo) * 0.08; lo -= pad; hi += pad;
    const t0 = Math.min(ts[0], t1 - 60);
    const x = function (t) { return L + (W - L - R) * (t - t0) / Math.max(1, t1 - t0); };
    const y = function (v) { return T + (H - T - B) * (1 - (v - lo) / (hi - lo)); };
    for (const v of [lo + pad, (lo + hi) / 2, hi - pad]) {
      svg.appendChild(svgEl("line", { class: "grid", x1: L, x2: W - R, y1: y(v), y2: y(v) }));
      const lab = svgEl("text", { x: L - 4, y: y(v) + 3, "text-anchor": "end" });
      lab.textContent = fmt(v, f.precision);
      svg.appendChild(lab);
    }
    const left = svgEl("text", { x: L, y: H - 4 });
    left.textContent = "−" + ago(t1 - t0);
    svg.appendChild(left);
    const right = svgEl("text", { x: W - R, y: H - 4, "text-anchor": "end" });
    right.textContent = "now";
    svg.appendChild(right);
    const pts = ts.map(function (t, i) { return x(t).toFixed(1) + "," + y(vs[i]).toFixed(1); }).join(" ");
    svg.appendChild(svgEl("polyline", { class: "line", points: pts }));
    const last = svgEl("circle", { class: "dot", cx: x(ts[ts.length - 1]), cy: y(vs[vs.length - 1]), r: 2.5 });
    svg.appendChild(last);
    td.appendChild(svg);
    const note = el("div", "chart-note", ts.length + " points · min " + fmt(Math.min.apply(null, vs), f.precision) +
      " · max " + fmt(Math.max.apply(null, vs), f.precision) + (f.unit ? " " + f.unit : ""));
    td.appendChild(note);
  }

  function fmt(v, precision) {
    if (typeof precision === "number" && precision >= 0) return v.toFixed(Math.min(precision, 6));
    const a = Math.abs(v);
    return a >= 1000 ? v.toFixed(0) : a >= 10 ? v.toFixed(1) : v.toPrecision(3);
  }

  function findField(key, name) {
    const d = findDevice(key);
    if (!d) return null;
    for (const f of d.dev.fields) if (f.name === name) return f;
    return null;
  }

  function toggle(row) {
    const card = row.closest(".device");
    if (!card) return;
    const key = card.dataset.key, name = row.dataset.field;
    const k = key + SEP + name;
    const f = findField(key, name);
    if (!f) return;
    if (open.has(k)) {
      open.delete(k);
      row.classList.remove("open");
      const next = row.nextElementSibling;
      if (next && next.classList.contains("chart-row")) next.remove();
      fit(card);
      return;
    }
    open.add(k);
    row.classList.add("open");
    row.after(chartRow(k, f));
    drawCharts(card);
    fit(card);
    fetch("/api/trend?device=" + encodeURIComponent(key) + "&field=" + encodeURIComponent(name), { credentials: "same-origin" })
      .then(function (r) { if (!r.ok) throw new Error("trend: HTTP " + r.status); return r.json(); })
      .then(function (data) {
        const have = series.get(k);
        if (have) { // points that came by events meanwhile
          const lastT = data.t.length ? data.t[data.t.length - 1] : -Infinity;
          for (let i = 0; i < have.t.length; i++) if (have.t[i] > lastT) { data.t.push(have.t[i]); data.v.push(have.v[i]); }
        }
        series.set(k, data);
        redraw(k);
      })
      .catch(function (e) { console.warn(String(e)); });
  }

  function redraw(k) {
    const tr = document.querySelector('tr.chart-row[data-chart="' + CSS.escape(k) + '"]');
    if (tr) { drawRow(tr); fit(tr.closest(".device")); }
  }

  function drawRow(tr) {
    const k = tr.dataset.chart;
    const parts = k.split(SEP);
    const f = findField(parts[0], parts[1]);
    if (f) draw(tr.firstChild, k, f);
  }

  function drawCharts(root) {
    for (const tr of root.querySelectorAll("tr.chart-row")) drawRow(tr);
  }

  // each card spans as many 4 px grid rows as it is tall (+ the gap): columns of
  // cards of different heights without holes under the short ones
  const ROW = 4, GAP = 12;
  function fit(root) {
    const cards = root.classList && root.classList.contains("device") ? [root] : root.querySelectorAll(".device");
    for (const c of cards) {
      const rows = Math.ceil((c.getBoundingClientRect().height + GAP) / ROW);
      if (c.dataset.rows !== String(rows)) { c.dataset.rows = String(rows); c.style.gridRowEnd = "span " + rows; }
    }
  }
  window.addEventListener("resize", function () { fit(app); });

  // -- the model ------------------------------------------------------------------

  function findDevice(key) {
    if (!state) return null;
    for (const gw of state.gateways) for (const bus of gw.buses) {
      for (let i = 0; i < bus.devices.length; i++) if (bus.devices[i].key === key) return { gw: gw, bus: bus, i: i, dev: bus.devices[i] };
    }
    return null;
  }

  // a device event is merged into the model at once (it carries only the fields whose
  // reading changed, and every field's reading time); the cards that changed are drawn
  // once per frame: a page in a background tab (no frames) holds a set of keys, never
  // a backlog, and the layout is computed once per frame, not once per event
  const dirty = new Map(); // device key -> {t: newest reading time, changed: Set of names | null}
  let scheduled = false;
  function queue(msg) {
    const t = merge(msg);
    if (t === null) return;
    const d = dirty.get(msg.device.key);
    const names = msg.device.fields ? msg.device.fields.map(function (f) { return f.name; }) : [];
    if (d) { d.t = t; if (d.changed) for (const n of names) d.changed.add(n); }
    else dirty.set(msg.device.key, { t: t, changed: new Set(names) });
    if (!scheduled) { scheduled = true; requestAnimationFrame(flush); }
  }
  function flush() {
    scheduled = false;
    const started = performance.now();
    const cards = [];
    let all = false;
    for (const [key, d] of dirty) {
      const at = findDevice(key);
      if (!at) continue;
      const old = app.querySelector('.device[data-key="' + CSS.escape(key) + '"]');
      if (old) cards.push(updateDevice(old, at.gw, at.dev, d.changed));
      else all = true;
    }
    const n = dirty.size;
    const polled = Array.from(dirty.values(), function (d) { return d.t; });
    perf.events += n;
    dirty.clear();
    if (all) renderAll();
    for (const c of cards) fit(c);
    summary();
    const done = Date.now() / 1000;
    for (const t of polled) if (t) note(perf.latency, done - t);
    if (n) note(perf.update, (performance.now() - started) / n);
  }

  // an event's device into the snapshot's: its fields replace those of the same name
  // (keeping their label, unit, kind ...), the others stay; `times` sets every field's
  // reading time (in the snapshot's field order), `health` is merged, the rest replaced
  function merge(msg) {
    const d = msg.device;
    const at = findDevice(d.key);
    if (!at) return null; // not in the snapshot (a reload sends a new one)
    const dev = at.dev;
    const index = new Map();
    dev.fields.forEach(function (f, i) { index.set(f.name, i); });
    let t = 0;
    for (const f of d.fields || []) {
      const i = index.get(f.name);
      if (i !== undefined) dev.fields[i] = Object.assign({}, dev.fields[i], f);
      if (f.time && f.time > t) t = f.time;
    }
    if (d.times) {
      d.times.forEach(function (time, i) {
        if (time !== null && i < dev.fields.length) dev.fields[i].time = time;
        if (time && time > t) t = time;
      });
    }
    for (const k of Object.keys(d)) {
      if (k === "fields" || k === "times") continue;
      if (k === "health" && dev.health && d.health) Object.assign(dev.health, d.health);
      else dev[k] = d[k];
    }
    const span = state.span;
    for (const f of dev.fields) {
      const k = dev.key + SEP + f.name;
      const s = series.get(k);
      if (s && f.kind === "number" && typeof f.value === "number" && f.time) {
        const n = s.t.length, step = state.step || 2;
        if (n && Math.floor(f.time / step) === Math.floor(s.t[n - 1] / step)) {
          if (f.time >= s.t[n - 1]) { s.t[n - 1] = f.time; s.v[n - 1] = f.value; } // the same step: the newer
        } else if (!n || f.time > s.t[n - 1]) { s.t.push(f.time); s.v.push(f.value); }
        while (s.t.length && s.t[0] < now() - span) { s.t.shift(); s.v.shift(); }
      }
    }
    return t;
  }

  function onBuses(msg) {
    if (!state) return;
    for (const gw of state.gateways) {
      if (gw.id !== msg.gateway) continue;
      for (const b of msg.buses) {
        const bus = gw.buses.find(function (x) { return x.name === b.name; });
        if (!bus) continue;
        Object.assign(bus, b, { devices: bus.devices });
        const sec = app.querySelector('#' + CSS.escape("gw-" + gw.id) + ' .bus[data-bus="' + CSS.escape(b.name) + '"]');
        if (sec) {
          fillBusMeta(sec.querySelector(".bus-meta"), bus);
          fillServed(sec.querySelector(".served"), bus.gateway);
        }
      }
    }
  }

  function summary() {
    let n = 0, up = 0, gws = 0;
    for (const gw of state.gateways) {
      gws++;
      for (const bus of gw.buses) for (const d of bus.devices) { n++; if (d.state === "online" && gw.online) up++; }
    }
    let text = (state.mode === "fleet" ? gws + (gws === 1 ? " gateway · " : " gateways · ") : "") +
      up + " of " + n + " devices online";
    if (state.broker && state.broker !== "connected") text += " · broker " + state.broker;
    document.getElementById("summary").textContent = text;
    document.title = "rtupoll · " + up + "/" + n + " online";
  }

  // every second: ages and countdowns, without waiting for the next event
  function tick() {
    for (const s of app.querySelectorAll(".seen")) s.textContent = seenText(s.dataset.seen === "" ? null : Number(s.dataset.seen));
    if (!state) return;
    for (const card of app.querySelectorAll(".device.down")) {
      const at = findDevice(card.dataset.key);
      const b = card.querySelector(".state");
      if (at && b) b.textContent = stateText(at.dev);
    }
  }

  // -- the stream -----------------------------------------------------------------

  function connect() {
    const es = new EventSource("/api/events");
    es.addEventListener("open", function () { conn.dataset.state = "live"; conn.textContent = "live"; });
    es.addEventListener("error", function () { conn.dataset.state = "lost"; conn.textContent = "reconnecting…"; });
    es.addEventListener("state", function (e) {
      dirty.clear();
      state = JSON.parse(e.data);
      offset = state.time - Date.now() / 1000;
      renderAll();
    });
    es.addEventListener("device", function (e) { queue(JSON.parse(e.data)); });
    es.addEventListener("buses", function (e) { onBuses(JSON.parse(e.data)); });
  }

  app.addEventListener("click", function (e) {
    const row = e.target.closest("tr.num");
    if (row) toggle(row);
  });
  app.addEventListener("keydown", function (e) {
    if (e.key !== "Enter" && e.key !== " ") return;
    const row = e.target.closest("tr.num");
    if (row) { e.preventDefault(); toggle(row); }
  });
  setInterval(tick, 1000);
  connect();
})();
