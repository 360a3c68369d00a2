// The operator page's live updates: server-sent events carry the run's state; this script only
// renders it and posts the operator's answers (with the page's CSRF value).
(function () {
  "use strict";
  var app = document.getElementById("app");
  if (!app) { return; }
  var csrf = document.querySelector('meta[name="csrf-token"]').getAttribute("content");
  var state = JSON.parse(app.getAttribute("data-state"));
  var $ = function (id) { return document.getElementById(id); };

  function post(url, body) {
    return fetch(url, {
      method: "POST",
      headers: {"Content-Type": "application/json", "X-CSRF-Token": csrf},
      body: JSON.stringify(body || {}),
      credentials: "same-origin"
    }).then(function (r) {
      return r.json().catch(function () { return {}; }).then(function (data) {
        if (!r.ok) { throw new Error(data.error || ("HTTP " + r.status)); }
        return data;
      });
    });
  }

  function showError(message) {
    var el = $("start-error");
    el.textContent = message;
    el.hidden = false;
  }

  // "12 s", "2 min 05 s": the pages' one copy of calstation.display.duration (status.js)
  var duration = window.calstationStatus.duration;

  // writes only where something changed: a text, class or flag written again unchanged still
  // costs the browser a style pass, a layout and a paint, a few times a second for the run
  function setText(el, text) { if (el.textContent !== text) { el.textContent = text; } }
  function setHidden(el, hidden) { if (el.hidden !== hidden) { el.hidden = hidden; } }
  function setClass(el, cls) { if (el.className !== cls) { el.className = cls; } }

  // a new run: nothing of the previous one stays on the page (its end screen, log, plot, steps)
  function resetRun(s) {
    $("result").hidden = true;
    $("result").innerHTML = "";
    $("log").innerHTML = "";
    $("accuracy-live").hidden = true;
    var plot = $("line-plot");
    plot.innerHTML = "";
    plot.hidden = true;
    plot.removeAttribute("data-seq");
    plot.removeAttribute("data-drawn");
    plot.removeAttribute("data-key");
    resetCloud(null);
    $("cloud-plot").hidden = true;
    var list = $("steps");
    list.innerHTML = "";
    s.steps.forEach(function (st) {
      var li = document.createElement("li");
      li.setAttribute("data-step", st.name);
      ["title", "attempt", "seconds"].forEach(function (cls) {
        var span = document.createElement("span");
        span.className = cls;
        li.appendChild(span);
      });
      li.querySelector(".title").textContent = st.title;
      list.appendChild(li);
    });
    $("prompt").removeAttribute("data-prompt");
  }

  // the server's clock minus this browser's, so that the elapsed time is the server's
  var skew = 0;
  function tickElapsed() {
    var el = $("run-elapsed");
    if (!state.started_at) { setText(el, "—"); return; }
    var end = state.finished_at || (Date.now() / 1000 + skew);
    setText(el, duration(end - state.started_at));
  }

  // every clock of the page (elapsed, the running step's time, how long the station has been
  // held) in one pass, so that a second's change of them all is one frame
  function tickClocks() {
    tickElapsed();
    var running = document.querySelector("#steps li.running .seconds");
    var st = state.steps.filter(function (x) { return x.status === "running"; })[0];
    if (running && st && st.started_at) { setText(running, " " + duration(Date.now() / 1000 + skew - st.started_at)); }
    if (window.calstationStatus) { window.calstationStatus.tick(); }
  }

  // the clocks tick a second after they were last drawn: a running scan's states (twice a
  // second) carry them along in their own frames, and only a quiet page (a prompt) draws a
  // frame a second for its clocks alone
  var clockTimer = null;
  function armClocks() {
    if (clockTimer) { window.clearTimeout(clockTimer); }
    clockTimer = window.setTimeout(function () {
      clockTimer = null;
      if (!document.hidden) { tickClocks(); }
      armClocks();
    }, 1000);
  }

  function renderLog(lines) {
    var list = $("log");
    var last = lines.length ? lines[lines.length - 1].text : null;
    if (list.children.length === lines.length &&
        (last === null || (list.lastChild && list.lastChild.textContent === last))) { return; }
    list.innerHTML = "";
    lines.forEach(function (l) {
      var li = document.createElement("li");
      li.className = l.level;
      li.textContent = l.text;
      list.appendChild(li);
    });
  }

  // who holds each station (every page's status line) and whether Start may be pressed
  var stationsKey = null;
  function renderStations(stations) {
    var key = JSON.stringify(stations || []);
    if (key === stationsKey) { return; }
    stationsKey = key;
    if (window.calstationStatus) { window.calstationStatus.render(stations || []); }
    startAvailability();
  }

  function startAvailability() {
    var select = $("recipe"), button = $("start-button"), note = $("start-blocked");
    if (!select || !button) { return; }
    var option = select.options[select.selectedIndex];
    var station = option ? option.getAttribute("data-station") : null;
    var held = (state.stations || []).filter(function (x) { return x.held && x.station === station; })[0];
    button.disabled = !option || !!held;
    note.hidden = !held;
    note.textContent = held ? "Start is unavailable: " + held.text +
      ". Wait for that run to end, or abort it where it was started." : "";
    var d = $("recipe-description");
    if (d && option) {
      d.textContent = (option.getAttribute("data-description") || "No description.") + " Station " +
        station + "; the platter turns " + option.getAttribute("data-scan") + " at the least.";
    }
  }

  function render(s) {
    var previous = state;
    state = s;
    if (s.run_id !== previous.run_id || (s.busy && !previous.busy)) { resetRun(s); }
    app.setAttribute("data-status", s.status);
    app.setAttribute("data-version", String(s.version));
    setHidden($("start"), s.busy);
    setHidden($("run"), s.status === "idle");
    setText($("run-id"), String(s.run_id || ""));
    setText($("run-status"), s.status);
    setClass($("run-status"), "status " + s.status);
    setText($("run-recipe"), s.recipe || "");
    setText($("run-operator"), s.operator || "");
    setText($("run-serial"), s.serial || "from the lidar");
    renderLog(s.log || []);
    s.steps.forEach(function (st) {
      var li = document.querySelector('#steps li[data-step="' + st.name + '"]');
      if (!li) { return; }
      setClass(li, st.status + (st.name === s.step && s.busy ? " current" : ""));
      setText(li.querySelector(".attempt"), st.attempt > 1 ? " (attempt " + st.attempt + ")" : "");
      var secs = st.seconds;
      if (st.status === "running" && st.started_at) { secs = Date.now() / 1000 + skew - st.started_at; }
      setText(li.querySelector(".seconds"), secs === null || secs === undefined ? "" : " " + duration(secs));
    });
    setHidden($("abort-button"), !s.busy);
    renderPrompt(s.prompt);
    var p = s.progress;
    setHidden($("progress"), !p || !s.busy || !!s.prompt);
    if (p) {
      setText($("progress-text"), p.title + (p.phase ? ": " + p.phase : "") + " — " + Math.round(p.fraction * 100) + " %");
      if ($("progress-bar").value !== p.fraction) { $("progress-bar").value = p.fraction; }
    }
    renderStations(s.stations);
    renderLine(s.line, s.outline, s.busy);
    renderCloud(s.busy ? s.cloud : null);
    renderAccuracy(s.accuracy || [], s.busy);
    tickClocks();
    armClocks();
    if (previous.busy && !s.busy) {
      // the run ended: the end screen (values beside their limits) is rendered by the server
      window.location.reload();
    }
  }

  // the predicted error after each turn of the scan under way, beside the budget
  function renderAccuracy(points, busy) {
    var box = $("accuracy-live");
    if (!box) { return; }
    setHidden(box, !busy || points.length === 0);
    if (box.hidden) { return; }
    // the words and numbers are the server's (calstation.display); the page only joins them
    var last = points[points.length - 1];
    setText(box, "predicted error of the " + last.scan.replace("_", " ") + " after " +
      points.map(function (a) { return a.text; }).join(", ") + " (budget " + last.budget_text + ")");
    setClass(box, last.within ? "ok" : "pending");
  }

  function renderPrompt(p) {
    var box = $("prompt");
    if (!p) { setHidden(box, true); box.removeAttribute("data-prompt"); return; }
    setHidden(box, false);
    if (box.getAttribute("data-prompt") === String(p.id)) { return; }
    box.setAttribute("data-prompt", String(p.id));
    box.setAttribute("data-kind", p.kind);
    box.setAttribute("data-fixture", p.fixture || "");
    box.setAttribute("data-step", p.step || "");
    $("prompt-title").textContent = p.title || (p.kind === "failure" ? "The step failed" : "Place the fixture");
    $("prompt-text").textContent = p.text;
    $("prompt-error").hidden = !p.error;
    $("prompt-error").textContent = p.error || "";
    $("prompt-svg").innerHTML = p.svg || "";  // drawn by the server from the recipe, escaped there
    box.querySelectorAll("button[data-answer]").forEach(function (b) {
      b.hidden = p.answers.indexOf(b.getAttribute("data-answer")) < 0;
      b.disabled = false;
    });
  }

  // the plots are the page's heavy work: none while the page cannot be seen (another tab, a
  // minimised window) or the plot is scrolled away; the latest state is drawn on return
  function shown(el) { return !document.hidden && el.getAttribute("data-in-view") !== "no"; }
  var watcher = window.IntersectionObserver ? new IntersectionObserver(function (entries) {
    entries.forEach(function (e) {
      e.target.setAttribute("data-in-view", e.isIntersecting ? "yes" : "no");
      if (e.isIntersecting) { redraw(); }
    });
  }) : null;
  ["line-plot", "cloud-plot"].forEach(function (id) { if (watcher) { watcher.observe($(id)); } });
  function redraw() {
    renderLine(state.line, state.outline, state.busy);
    renderCloud(state.busy ? state.cloud : null);
  }
  document.addEventListener("visibilitychange", function () {
    document.body.setAttribute("data-visible", document.hidden ? "no" : "yes");
    if (!document.hidden) { redraw(); }
  });

  function renderLine(line, outline, busy) {
    var el = $("line-plot");
    if (!line || !busy) { setHidden(el, true); return; }
    setHidden(el, false);
    if (!shown(el)) { return; }
    var key = String(line.seq) + "/" + (outline ? outline.source + "/" + outline.platter_angle_deg + "/" + outline.lines.length : "");
    if (el.getAttribute("data-key") === key) { return; }
    el.setAttribute("data-key", key);
    el.setAttribute("data-seq", String(line.seq));
    var title = "live lidar line (" + line.kind + " scan, " + line.points + " returns)";
    var subtitle = "";
    var plotted = [{name: "returns", x: line.x_mm, y: line.y_mm}];
    if (outline && outline.known) {
      // where the platter and the fixture should appear under the calibration known so far
      var ox = [], oy = [];
      outline.lines.forEach(function (l) { ox = ox.concat(l.x, [null]); oy = oy.concat(l.y, [null]); });
      plotted.push({name: "expected outline", x: ox, y: oy});
      subtitle = "dotted: the " + outline.fixture.replace(/_/g, " ") +
        " and the platter as expected under " + outline.source;
    } else if (outline) {
      subtitle = "no expected outline: " + outline.source;
    }
    // zoomed on what matters: the platter and its fixture where they are expected, else the
    // nearest returns (not the room)
    var win = line.window;
    if (outline && outline.known && outline.lines.length) {
      var xs = [], ys = [];
      outline.lines.forEach(function (l) { xs = xs.concat(l.x); ys = ys.concat(l.y); });
      var pad = 120;
      win = {x: [Math.min.apply(null, xs) - pad, Math.max.apply(null, xs) + pad],
             y: [Math.min.apply(null, ys) - pad, Math.max.apply(null, ys) + pad]};
    }
    drawLine(el, title, subtitle, plotted, win, !!(outline && !outline.known));
    el.plotted = plotted;  // what is drawn, for whoever inspects the page
    el.setAttribute("data-drawn", "1");
    el.setAttribute("data-draws", String(Number(el.getAttribute("data-draws") || 0) + 1));
    el.setAttribute("data-outline", outline ? (outline.known ? "expected" : "unknown") : "none");
  }

  // a round step for about n ticks over span
  function tickStep(span, n) {
    var raw = span / n, mag = Math.pow(10, Math.floor(Math.log10(raw))), f = raw / mag;
    return mag * (f < 1.5 ? 1 : f < 3.5 ? 2 : f < 7.5 ? 5 : 10);
  }

  // the live line on a plain canvas (frame L, mm, one scale on both axes): redrawn twice a
  // second, it costs a few milliseconds where a plotting library's redraw cost tens
  function drawLine(el, title, subtitle, plotted, win, warn) {
    var width = Math.max(320, el.clientWidth || 640), height = 340;
    var head = el.querySelector("p.line-title"), sub = el.querySelector("p.line-subtitle");
    var canvas = el.querySelector("canvas");
    if (!canvas) {
      head = document.createElement("p");
      head.className = "line-title";
      sub = document.createElement("p");
      sub.className = "line-subtitle";
      canvas = document.createElement("canvas");
      el.appendChild(head);
      el.appendChild(sub);
      el.appendChild(canvas);
    }
    setText(head, title);
    setText(sub, subtitle);
    setClass(sub, "line-subtitle" + (warn ? " warn" : ""));
    // a new size only when the plot's width changed (a new size is a new bitmap)
    if (canvas.width !== width) { canvas.width = width; }
    if (canvas.height !== height) { canvas.height = height; }
    var ctx = canvas.getContext("2d");
    ctx.save();
    ctx.fillStyle = "#ffffff";
    ctx.fillRect(0, 0, width, height);
    var left = 58, right = 12, top = 8, bottom = 38;
    var pts = plotted[0];
    if (!win) {
      win = {x: [Math.min.apply(null, pts.x), Math.max.apply(null, pts.x)],
             y: [Math.min.apply(null, pts.y), Math.max.apply(null, pts.y)]};
    }
    // one scale for both axes, the window centred
    var w = width - left - right, h = height - top - bottom;
    var sx = w / Math.max(1, win.x[1] - win.x[0]), sy = h / Math.max(1, win.y[1] - win.y[0]);
    var k = Math.min(sx, sy);
    var cx = (win.x[0] + win.x[1]) / 2, cy = (win.y[0] + win.y[1]) / 2;
    var X = function (x) { return left + w / 2 + (x - cx) * k; };
    var Y = function (y) { return top + h / 2 - (y - cy) * k; };
    var x0 = cx - w / 2 / k, x1 = cx + w / 2 / k, y0 = cy - h / 2 / k, y1 = cy + h / 2 / k;
    // grid, ticks and the axes' names
    ctx.font = "11px system-ui, sans-serif";
    ctx.strokeStyle = "#eaeef2";
    ctx.fillStyle = "#57606a";
    var step = tickStep(Math.max(x1 - x0, y1 - y0), 6), t;
    for (t = Math.ceil(x0 / step) * step; t <= x1; t += step) {
      ctx.beginPath(); ctx.moveTo(X(t), top); ctx.lineTo(X(t), top + h); ctx.stroke();
      ctx.fillText(String(Math.round(t)), X(t) - 12, top + h + 13);
    }
    ctx.textAlign = "right";
    for (t = Math.ceil(y0 / step) * step; t <= y1; t += step) {
      ctx.beginPath(); ctx.moveTo(left, Y(t)); ctx.lineTo(left + w, Y(t)); ctx.stroke();
      ctx.fillText(String(Math.round(t)), left - 4, Y(t) + 4);
    }
    ctx.textAlign = "left";
    ctx.strokeStyle = "#8c959f";
    ctx.strokeRect(left, top, w, h);
    ctx.fillStyle = "#1b1f24";
    ctx.fillText("x_L (mm)", left + w / 2 - 20, height - 6);
    ctx.save();
    ctx.translate(11, top + h / 2);
    ctx.rotate(-Math.PI / 2);
    ctx.textAlign = "center";
    ctx.fillText("y_L (mm, boresight)", 0, 0);
    ctx.restore();
    ctx.save();
    ctx.beginPath();
    ctx.rect(left, top, w, h);
    ctx.clip();
    ctx.fillStyle = "#0969da";
    for (var i = 0; i < pts.x.length; i++) { ctx.fillRect(X(pts.x[i]) - 1.5, Y(pts.y[i]) - 1.5, 3, 3); }
    if (plotted.length > 1) {
      var o = plotted[1];
      ctx.strokeStyle = "#e36209";
      ctx.lineWidth = 2;
      ctx.setLineDash([3, 4]);
      ctx.beginPath();
      var pen = false;
      for (i = 0; i < o.x.length; i++) {
        if (o.x[i] === null) { pen = false; continue; }
        if (pen) { ctx.lineTo(X(o.x[i]), Y(o.y[i])); } else { ctx.moveTo(X(o.x[i]), Y(o.y[i])); pen = true; }
      }
      ctx.stroke();
    }
    ctx.restore();
    ctx.restore();
  }

  // the scan's cloud under the calibration known so far, growing as the platter turns: only
  // the new points are fetched, at most every CLOUD_PERIOD_MS. It is drawn on a plain canvas,
  // seen from a fixed angle and coloured by height: a 3D plot's WebGL redraws itself many times
  // a second while it is shown, which without a graphics processor costs the run more than the
  // whole page otherwise does (the report has the 3D view to turn)
  var CLOUD_PERIOD_MS = 3000;
  var CLOUD_SHADES = 24;  // colours of the height scale
  var cloud = {id: null, n: 0, shown: 0, title: "", fetching: false, drawn: 0, timer: null,
               x: [], y: [], z: []};
  function renderCloud(meta) {
    var el = $("cloud-plot");
    if (!meta) { setHidden(el, true); return; }
    setHidden(el, false);
    if (meta.id !== cloud.id) { resetCloud(meta.id); }
    if (!shown(el)) { return; }
    if (cloud.n > cloud.shown) { drawCloud(el); }  // fetched while it could not be seen
    if (meta.count <= cloud.n) { return; }
    var wait = cloud.drawn + CLOUD_PERIOD_MS - Date.now();
    if (wait <= 0) { fetchCloud(); return; }
    if (!cloud.timer) {
      cloud.timer = window.setTimeout(function () {
        cloud.timer = null;
        renderCloud(state.busy ? state.cloud : null);
      }, wait);
    }
  }

  function resetCloud(id) {
    var el = $("cloud-plot");
    el.innerHTML = "";
    el.removeAttribute("data-points");
    if (cloud.timer) { window.clearTimeout(cloud.timer); }
    cloud = {id: id, n: 0, shown: 0, title: "", fetching: cloud.fetching, drawn: 0, timer: null,
             x: [], y: [], z: []};
  }

  function fetchCloud() {
    if (cloud.fetching) { return; }
    cloud.fetching = true;
    cloud.drawn = Date.now();
    fetch("/cloud.json?cloud=" + (cloud.id || 0) + "&since=" + cloud.n, {credentials: "same-origin"})
      .then(function (r) { return r.json(); })
      .then(function (c) {
        if (c.id === null) { return; }
        if (c.id !== cloud.id) { resetCloud(c.id); }
        if (c.start !== cloud.n || c.x.length === 0) { return; }
        cloud.x = cloud.x.concat(c.x);
        cloud.y = cloud.y.concat(c.y);
        cloud.z = cloud.z.concat(c.z);
        cloud.n += c.x.length;
        cloud.title = c.scan + " scan reconstructed under " + c.source;
        if (shown($("cloud-plot"))) { drawCloud($("cloud-plot")); }
      })
      .catch(function () { /* the next state retries */ })
      .finally(function () {
        cloud.fetching = false;
        renderCloud(state.busy ? state.cloud : null);  // more came meanwhile: when it is due
      });
  }

  // viridis, five stops: low (dark blue) to high (yellow)
  var VIRIDIS = [[68, 1, 84], [59, 82, 139], [33, 145, 140], [94, 201, 98], [253, 231, 37]];
  function colour(t) {
    var f = Math.max(0, Math.min(1, t)) * (VIRIDIS.length - 1), i = Math.min(VIRIDIS.length - 2, Math.floor(f));
    var a = VIRIDIS[i], b = VIRIDIS[i + 1], w = f - i;
    return "rgb(" + [0, 1, 2].map(function (k) { return Math.round(a[k] + (b[k] - a[k]) * w); }).join(",") + ")";
  }

  function drawCloud(el) {
    var title = cloud.title;
    cloud.shown = cloud.n;
    var width = Math.max(320, el.clientWidth || 640), height = 380;
    var heading = el.querySelector("p.cloud-title"), canvas = el.querySelector("canvas");
    if (!canvas) {
      heading = document.createElement("p");
      heading.className = "cloud-title";
      canvas = document.createElement("canvas");
      el.appendChild(heading);
      el.appendChild(canvas);
    }
    heading.textContent = title + " (" + cloud.n + " points; seen from above and aside, " +
      "coloured by height x_D: dark low, yellow high)";
    canvas.width = width;
    canvas.height = height;
    var ctx = canvas.getContext("2d");
    ctx.fillStyle = "#ffffff";
    ctx.fillRect(0, 0, width, height);
    // frame D: x_D up; the platter's plane (y_D, z_D) seen at 30° from above, turned 45°
    var c45 = Math.SQRT1_2, s30 = 0.5, c30 = Math.sqrt(3) / 2;
    var u = [], v = [], lo = Infinity, hi = -Infinity, i;
    for (i = 0; i < cloud.n; i++) {
      var a = (cloud.y[i] - cloud.z[i]) * c45, d = (cloud.y[i] + cloud.z[i]) * c45;
      u.push(a);
      v.push(-cloud.x[i] * c30 + d * s30);
      lo = Math.min(lo, cloud.x[i]);
      hi = Math.max(hi, cloud.x[i]);
    }
    var umin = Math.min.apply(null, u), umax = Math.max.apply(null, u);
    var vmin = Math.min.apply(null, v), vmax = Math.max.apply(null, v);
    var scale = Math.min((width - 60) / Math.max(1, umax - umin), (height - 50) / Math.max(1, vmax - vmin));
    var ox = (width - (umax - umin) * scale) / 2, oy = (height - (vmax - vmin) * scale) / 2;
    // the points by height in CLOUD_SHADES bands, each band drawn in one colour at once
    var bands = [];
    for (i = 0; i < CLOUD_SHADES; i++) { bands.push([]); }
    for (i = 0; i < cloud.n; i++) {
      var t = (cloud.x[i] - lo) / Math.max(1e-9, hi - lo);
      bands[Math.min(CLOUD_SHADES - 1, Math.floor(t * CLOUD_SHADES))].push(i);
    }
    bands.forEach(function (band, k) {
      if (!band.length) { return; }
      ctx.fillStyle = colour((k + 0.5) / CLOUD_SHADES);
      ctx.beginPath();
      // on whole pixels: crisp dots, no colour blended from a neighbour's edge
      band.forEach(function (j) { ctx.rect(Math.round(ox + (u[j] - umin) * scale), Math.round(oy + (v[j] - vmin) * scale), 2, 2); });
      ctx.fill();
    });
    // the axes' directions, bottom left, inside the picture
    var ax = 52, ay = height - 26;
    ctx.strokeStyle = "#57606a";
    ctx.fillStyle = "#1b1f24";
    ctx.font = "11px system-ui, sans-serif";
    [["y_D", c45, c45 * s30], ["z_D", -c45, c45 * s30], ["x_D (up)", 0, -c30]].forEach(function (d) {
      ctx.beginPath();
      ctx.moveTo(ax, ay);
      ctx.lineTo(ax + d[1] * 22, ay + d[2] * 22);
      ctx.stroke();
      ctx.fillText(d[0], ax + d[1] * 26 - (d[1] < 0 ? 22 : 0), ay + d[2] * 26 + 4);
    });
    el.setAttribute("data-points", String(cloud.n));
    el.setAttribute("data-draws", String(Number(el.getAttribute("data-draws") || 0) + 1));
  }

  $("recipe").addEventListener("change", startAvailability);

  $("start-form").addEventListener("submit", function (ev) {
    ev.preventDefault();
    $("start-error").hidden = true;
    $("start-button").disabled = true;
    try { window.localStorage.setItem("calstation-operator", $("operator").value); } catch (e) { /* private mode */ }
    post("/api/start", {recipe: $("recipe").value, operator: $("operator").value, serial: $("serial").value})
      .then(function (data) { render(data.state); })
      .catch(function (e) { showError(e.message); })
      .finally(function () { startAvailability(); });
  });

  document.querySelectorAll("#prompt button[data-answer]").forEach(function (b) {
    b.addEventListener("click", function () {
      var id = Number($("prompt").getAttribute("data-prompt"));
      // the prompt's Abort ends the run as the Abort run button does: it asks first
      if (b.getAttribute("data-answer") === "abort" &&
          !window.confirm("Abort the run? The turntable is stopped.")) { return; }
      document.querySelectorAll("#prompt button[data-answer]").forEach(function (x) { x.disabled = true; });
      post("/api/answer", {prompt_id: id, answer: b.getAttribute("data-answer")})
        .catch(function (e) { alert(e.message); });
    });
  });

  $("abort-button").addEventListener("click", function () {
    if (!window.confirm("Abort the run? The turntable is stopped.")) { return; }
    post("/api/abort").catch(function (e) { alert(e.message); });
  });

  // this browser's operator, when the server knows none (the last run's is the default)
  try {
    var remembered = window.localStorage.getItem("calstation-operator");
    if (remembered && !$("operator").value) { $("operator").value = remembered; }
  } catch (e) { /* private mode */ }
  // the server renders the first state (its clock is the server's at that moment); prompts
  // shown on reload need their id
  if (state.now) { skew = state.now - Date.now() / 1000; }
  if (state.prompt) { $("prompt").removeAttribute("data-prompt"); }
  render(state);

  // on a station with a token the stream needs the logged-in session (the page says so)
  if (app.getAttribute("data-live") === "yes") {
    var source = new EventSource("/events");
    if (window.calstationStatus) { window.calstationStatus.live = true; }
    // the server's clock as each state is sent: a cached state's "now" is the time it changed
    source.addEventListener("clock", function (ev) {
      skew = Number(ev.data) - Date.now() / 1000;
      if (window.calstationStatus) { window.calstationStatus.setSkew(skew); }
      tickElapsed();
    });
    source.addEventListener("state", function (ev) {
      render(JSON.parse(ev.data));
      app.setAttribute("data-streamed", String(state.version));  // a state came over the stream
    });
    source.addEventListener("end", function () {
      source.close();  // the session ended (logged out, expired, new token)
      showError("Your session ended: log in again to follow the run.");
    });
  }
  window.addEventListener("load", function () {
    if (state.line) { renderLine(state.line, state.outline, state.busy); }
    if (state.busy && state.cloud) { renderCloud(state.cloud); }
  });
})();
