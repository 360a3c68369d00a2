// Draws the figures of a page: each element with data-figure="KEY" gets the plotly figure KEY
// of the JSON block #figures. A click on a point or a bar follows its link (customdata).
(function () {
  "use strict";
  var block = document.getElementById("figures");
  if (!block || !window.Plotly) { return; }
  var figures = JSON.parse(block.textContent);
  var pending = 0;
  document.querySelectorAll("[data-figure]").forEach(function (el) {
    var fig = figures[el.getAttribute("data-figure")];
    if (!fig) { return; }
    pending += 1;
    Plotly.newPlot(el, fig.data, fig.layout, {displaylogo: false, responsive: true})
      .then(function () {
        el.setAttribute("data-drawn", "1");
        pending -= 1;
        if (pending === 0) { document.body.setAttribute("data-figures-drawn", "1"); }
        el.on("plotly_click", function (ev) {
          var link = ev && ev.points && ev.points[0] && ev.points[0].customdata;
          if (typeof link === "string" && link.charAt(0) === "/") { window.location.href = link; }
        });
      });
  });
  if (pending === 0) { document.body.setAttribute("data-figures-drawn", "1"); }
})();
