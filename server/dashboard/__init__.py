"""The operator dashboard: a live web page of the building, its people, its maps and the server's health.

``hybridloc serve --http HOST:PORT`` runs it inside the server process (on the server's own Zenoh
session and database); ``hybridloc dashboard`` runs it beside a running server (a Zenoh client, as a
read-only operator user under ``--acl-devices``). Both are :class:`~.run.Dashboard`.

Modules: :mod:`.live` (the state and its coalescing push), :mod:`.feed` (Zenoh to the event loop),
:mod:`.data` (floor plans and radio-map coverage from the database), :mod:`.auth` (tokens, cookie,
Origin), :mod:`.app` (the Starlette application), :mod:`.run` (uvicorn in a thread). The page itself
is ``static/`` (plain ES modules and a vendored Leaflet, no build step). docs/dashboard.md describes it.
"""
