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

  // a new run: nothing of the previous one stays on the page (its end screen, log, plot, steps)
  function resetRun(s) {
    $("result").hidden = true;
    $("result").innerHTML = "";
    $("log").innerHTML = "";
    $("accuracy-live").hidden = true;
    var plot = $("line-plot");
    if (window.Plotly) { Plotly.purge(plot); }
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
    if (!state.started_at) { el.textContent = "—"; return; }
    var end = state.finished_at || (Date.now() / 1000 + skew);
    el.textContent = duration(end - state.started_at);
  }

  function renderLog(lines) {
    var list = $("log");
    if (list.children.length === lines.length) { return; }
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
    if (s.now) { skew = s.now - Date.now() / 1000; }
    if (s.run_id !== previous.run_id || (s.busy && !previous.busy)) { resetRun(s); }
    app.setAttribute("data-status", s.status);
    app.setAttribute("data-version", String(s.version));
    $("start").hidden = s.busy;
    $("run").hidden = s.status === "idle";
    $("run-id").textContent = s.run_id || "";
    $("run-status").textContent = s.status;
    $("run-status").className = "status " + s.status;
    $("run-recipe").textContent = s.recipe || "";
    $("run-operator").textContent = s.operator || "";
    $("run-serial").textContent = s.serial || "from the lidar";
    tickElapsed();
    renderLog(s.log || []);
    s.steps.forEach(function (st) {
      var li = document.querySelector('#steps li[data-step="' + st.name + '"]');
      if (!li) { return; }
      li.className = st.status + (st.name === s.step && s.busy ? " current" : "");
      li.querySelector(".attempt").textContent = st.attempt > 1 ? " (attempt " + st.attempt + ")" : "";
      var secs = st.seconds;
      if (st.status === "running" && st.started_at) { secs = Date.now() / 1000 + skew - st.started_at; }
      li.querySelector(".seconds").textContent = secs === null || secs === undefined ? "" : " " + duration(secs);
    });
    $("abort-button").hidden = !s.busy;
    renderPrompt(s.prompt);
    var p = s.progress;
    $("progress").hidden = !p || !s.busy || !!s.prompt;
    if (p) {
      $("progress-text").textContent = p.title + (p.phase ? ": " + p.phase : "") + " — " + Math.round(p.fraction * 100) + " %";
      $("progress-bar").value = p.fraction;
    }
    renderStations(s.stations);
    renderLine(s.line, s.outline, s.busy);
    renderCloud(s.busy ? s.cloud : null);
    renderAccuracy(s.accuracy || [], s.busy);
    if (previous.busy && !s.busy) {
      // the run ended: the end screen (values beside their limits) is rendered by the server
      window.location.reload();
    }
  }

  // the predicted error after each turn of the scan under way, beside the budget
  function renderAccuracy(points, busy) {
    var box = $("accuracy-live");
    if (!box) { return; }
    box.hidden = !busy || points.length === 0;
    if (box.hidden) { return; }
    // the words and numbers are the server's (calstation.display); the page only joins them
    var last = points[points.length - 1];
    box.textContent = "predicted error of the " + last.scan.replace("_", " ") + " after " +
      points.map(function (a) { return a.text; }).join(", ") + " (budget " + last.budget_text + ")";
    box.className = last.within ? "ok" : "pending";
  }

  function renderPrompt(p) {
    var box = $("prompt");
    if (!p) { box.hidden = true; box.removeAttribute("data-prompt"); return; }
    box.hidden = false;
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

  function renderLine(line, outline, busy) {
    var el = $("line-plot");
    if (!line || !busy || !window.Plotly) { el.hidden = !line || !busy; return; }
    el.hidden = false;
    var key = String(line.seq) + "/" + (outline ? outline.source + "/" + outline.platter_angle_deg + "/" + outline.lines.length : "");
    if (el.getAttribute("data-key") === key) { return; }
    el.setAttribute("data-key", key);
    el.setAttribute("data-seq", String(line.seq));
    // SVG, not WebGL: plotly's WebGL traces compile code at run time, which the page's
    // Content-Security-Policy does not allow (no eval)
    var data = [{x: line.x_mm, y: line.y_mm, mode: "markers", type: "scatter",
                 marker: {size: 3, color: "#0969da"}, name: "returns"}];
    var title = "live lidar line (" + line.kind + " scan, " + line.points + " returns)";
    var subtitle = "";
    var notes = [];
    if (outline && outline.known) {
      // where the platter and the fixture should appear under the calibration known so far
      var ox = [], oy = [];
      outline.lines.forEach(function (l) { ox = ox.concat(l.x, [null]); oy = oy.concat(l.y, [null]); });
      data.push({x: ox, y: oy, mode: "lines", type: "scatter", name: "expected outline",
                 line: {color: "#e36209", width: 2, dash: "dot"}, hoverinfo: "skip"});
      // a subtitle, not a styled span in the title: plotly would set that span's style
      // attribute, which the page's policy refuses
      subtitle = "dotted: the " + outline.fixture.replace(/_/g, " ") +
        " and the platter as expected under " + outline.source;
    } else if (outline) {
      notes.push({text: "no expected outline: " + outline.source, xref: "paper", yref: "paper",
                  x: 0.5, y: 0.98, showarrow: false, font: {color: "#9a6700"}});
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
    var layout = {title: {text: title, font: {size: 15},
                          subtitle: {text: subtitle, font: {size: 12}}},
                  height: 340, margin: {l: 50, r: 10, t: 55, b: 40},
                  xaxis: {title: {text: "x_L (mm)"}, range: win ? win.x : undefined},
                  yaxis: {title: {text: "y_L (mm, boresight)"}, scaleanchor: "x",
                          range: win ? win.y : undefined},
                  annotations: notes, showlegend: false};
    Plotly.react(el, data, layout, {displaylogo: false, responsive: true, staticPlot: false});
    el.setAttribute("data-drawn", "1");
    el.setAttribute("data-outline", outline ? (outline.known ? "expected" : "unknown") : "none");
  }

  // the scan's cloud under the calibration known so far, growing as the platter turns: only
  // the new points are fetched
  var cloud = {id: null, n: 0, fetching: false};
  function renderCloud(meta) {
    var el = $("cloud-plot");
    if (!meta || !window.Plotly) { el.hidden = !meta; return; }
    el.hidden = false;
    if (meta.id !== cloud.id) { resetCloud(meta.id); }
    if (meta.count > cloud.n) { fetchCloud(); }
  }

  function resetCloud(id) {
    var el = $("cloud-plot");
    if (window.Plotly) { Plotly.purge(el); }
    el.innerHTML = "";
    el.removeAttribute("data-points");
    cloud = {id: id, n: 0, fetching: cloud.fetching};
  }

  function fetchCloud() {
    if (cloud.fetching) { return; }
    cloud.fetching = true;
    fetch("/cloud.json?cloud=" + (cloud.id || 0) + "&since=" + cloud.n, {credentials: "same-origin"})
      .then(function (r) { return r.json(); })
      .then(function (c) {
        if (c.id === null) { return; }
        if (c.id !== cloud.id) { resetCloud(c.id); }
        if (c.start !== cloud.n || c.x.length === 0) { return; }
        var el = $("cloud-plot");
        // plotly's z is up: (y_D, z_D, x_D) so that the platter lies flat, as in the report
        if (cloud.n === 0) {
          Plotly.newPlot(el, [{type: "scatter3d", mode: "markers", x: c.y, y: c.z, z: c.x,
                               marker: {size: 1.5, color: c.x, colorscale: "Viridis"}, name: "cloud"}],
            {title: {text: c.scan + " scan reconstructed under " + c.source, font: {size: 15}},
             height: 400, margin: {l: 0, r: 0, t: 40, b: 0}, showlegend: false,
             scene: {aspectmode: "data", camera: {eye: {x: 1.3, y: 1.3, z: 1.0}}, xaxis: {title: {text: "y_D (mm)"}},
                     yaxis: {title: {text: "z_D (mm)"}}, zaxis: {title: {text: "x_D (mm, up)"}}}},
            {displaylogo: false, responsive: true});
        } else {
          Plotly.extendTraces(el, {x: [c.y], y: [c.z], z: [c.x], "marker.color": [c.x]}, [0]);
        }
        cloud.n += c.x.length;
        el.setAttribute("data-points", String(cloud.n));
      })
      .catch(function () { /* the next state retries */ })
      .finally(function () {
        cloud.fetching = false;
        if (state.cloud && state.cloud.id === cloud.id && state.cloud.count > cloud.n) {
          window.setTimeout(fetchCloud, 200);
        }
      });
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
  window.setInterval(function () {
    if (state.busy) {
      tickElapsed();
      var running = document.querySelector("#steps li.running .seconds");
      var st = state.steps.filter(function (x) { return x.status === "running"; })[0];
      if (running && st && st.started_at) { running.textContent = " " + duration(Date.now() / 1000 + skew - st.started_at); }
    }
  }, 1000);

  // the server renders the first state; prompts shown on reload need their id
  if (state.prompt) { $("prompt").removeAttribute("data-prompt"); }
  render(state);

  // on a station with a token the stream needs the logged-in session (the page says so)
  if (app.getAttribute("data-live") === "yes") {
    var source = new EventSource("/events");
    if (window.calstationStatus) { window.calstationStatus.live = true; }
    source.addEventListener("state", function (ev) { render(JSON.parse(ev.data)); });
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
