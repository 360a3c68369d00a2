// The plan page: while a plan computes, check its state every 2 s and reload when it ends.
(function () {
  "use strict";
  var box = document.getElementById("plan-state");
  if (!box || box.getAttribute("data-status") !== "running") { return; }
  var timer = setInterval(function () {
    fetch("/plan.json", { credentials: "same-origin" })
      .then(function (r) { return r.json(); })
      .then(function (s) {
        if (s.status !== "running") { clearInterval(timer); window.location.reload(); return; }
        var p = document.getElementById("plan-progress");
        if (p) { p.textContent = "Planning " + s.recipe + ": " + s.progress_text + ". This page reloads when it is done."; }
      })
      .catch(function () { /* the next tick tries again */ });
  }, 2000);
})();
