// Every page's status line: who holds each station (run, operator, where from, since when).
// The operator page gets it with the run's state over its event stream (station.js calls
// render); other pages ask /station.json every few seconds while they are shown.
(function () {
  "use strict";
  var box = document.getElementById("station-status");
  var skew = 0;  // the server's clock minus this browser's
  if (box && box.getAttribute("data-now")) { skew = Number(box.getAttribute("data-now")) - Date.now() / 1000; }
  var shown = [];

  // "12 s", "2 min 05 s": calstation.display.duration, as the pages write it
  function duration(seconds) {
    if (seconds === null || seconds === undefined || !isFinite(seconds)) { return "—"; }
    seconds = Math.max(0, seconds);
    var tenths = Math.floor(seconds * 10 + 0.5);  // halves round up, as on the server
    if (tenths < 100) { return Math.floor(tenths / 10) + "." + (tenths % 10) + " s"; }
    var whole = Math.floor(seconds + 0.5);
    if (whole < 60) { return whole + " s"; }
    var pad = function (n) { return (n < 10 ? "0" : "") + n; };
    if (whole < 3600) { return Math.floor(whole / 60) + " min " + pad(whole % 60) + " s"; }
    return Math.floor(whole / 3600) + " h " + pad(Math.floor(whole % 3600 / 60)) + " min";
  }

  function tick() {
    if (!box) { return; }
    box.querySelectorAll(".age[data-since]").forEach(function (el) {
      var text = "(" + duration(Date.now() / 1000 + skew - Number(el.getAttribute("data-since"))) + ")";
      if (el.textContent !== text) { el.textContent = text; }  // unchanged: no layout, no paint
    });
  }

  function render(stations, now) {
    if (now) { skew = now - Date.now() / 1000; }
    shown = stations || [];
    if (!box) { return; }
    box.innerHTML = "";
    shown.forEach(function (s) {
      var p = document.createElement("p");
      p.className = "station " + (s.held ? "held" : "free");
      p.setAttribute("data-station", s.station);
      p.setAttribute("data-held", s.held ? "yes" : "no");
      var text = document.createElement("span");
      text.className = "text";
      text.textContent = s.text;
      p.appendChild(text);
      if (s.held) {
        var age = document.createElement("span");
        age.className = "age";
        age.setAttribute("data-since", String(s.holder.since_epoch));
        p.appendChild(document.createTextNode(" "));
        p.appendChild(age);
      }
      box.appendChild(p);
    });
    tick();
    document.dispatchEvent(new CustomEvent("calstation:stations", {detail: shown}));
  }

  // on the operator page (``live``) station.js ticks these clocks with its own, in one pass
  window.calstationStatus = {render: render, duration: duration, stations: function () { return shown; },
                             setSkew: function (s) { skew = s; tick(); }, tick: tick};

  if (!box) { return; }
  function poll() {
    if (document.hidden || window.calstationStatus.live) { return; }
    fetch("/station.json", {credentials: "same-origin"})
      .then(function (r) { return r.json(); })
      .then(function (d) { render(d.stations, d.now); })
      .catch(function () { /* the next tick tries again */ });
  }
  window.setInterval(poll, 5000);
  window.setInterval(function () { if (!document.hidden && !window.calstationStatus.live) { tick(); } }, 1000);
  document.addEventListener("visibilitychange", function () { if (!document.hidden) { poll(); } });
})();
