"""The web station: ``calstation serve``.

A FastAPI app with server-rendered Jinja2 pages and a JSON twin of every page:

- ``live``: the web front end of a run (an :class:`~calstation.station.operator.Operator` that
  keeps the run's live state for the pages and takes the operator's answers), and the
  one-run-at-a-time runner that executes a run in a background thread of the server process;
- ``placement``: the SVG top view of the platter drawn from the recipe's fixture geometry;
- ``security``: the station token and CSRF protection of state-changing requests;
- ``app``: the routes, grouped per area (operator, runs, trends, api).

The station logic stays in :mod:`calstation.station.run`; nothing here decides a step.
"""
