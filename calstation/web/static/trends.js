// The trend page's plot: the figure is data in the page (a JSON block), drawn by plotly.
(function () {
  "use strict";
  var data = document.getElementById("figure");
  var el = document.getElementById("trend-plot");
  if (!data || !el || !window.Plotly) { return; }
  var fig = JSON.parse(data.textContent);
  Plotly.newPlot(el, fig.data, fig.layout, {displaylogo: false, responsive: true})
    .then(function () { el.setAttribute("data-drawn", "1"); });
})();
