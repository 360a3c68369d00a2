"""The web station: ``calstation serve``.

A FastAPI app with server-rendered Jinja2 pages and a JSON twin of every page:

- ``live``: the web front end of a run (an :class:`~calstation.station.operator.Operator` that
  keeps the run's live state for the pages and takes the operator's answers), and the
  one-run-at-a-time runner that executes a run in a background thread of the server process;
- ``placement``: the SVG top view of the platter drawn from the recipe's fixture geometry;
- ``security``: who may change the station's state (the token, sessions, the cross-site
  checks), with ``tokens`` (the token and its file), ``sessions`` (session ids and the CSRF
  value bound to each), ``throttle`` (back-off of wrong tokens) and ``hosts`` (the ``Host``
  allow-list);
- ``middleware``: the front door around everything (host allow-list, body limit, security
  headers); ``payloads``: what request bodies may carry; ``events``: the live event streams;
  ``settings``: the limits;
- ``app``: the routes, grouped per area (operator, runs, trends, api).

docs/security.md has the threat model and what each module defends against.

The station logic stays in :mod:`calstation.station.machine`; nothing here decides a step.
"""
