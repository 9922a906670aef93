"""The operator's view: a read-only page served by the daemon (`[web]`) and `silo-agent report`.

`archive` reads the audit cache (scan list, history, one scan's layers and camera footprints),
`pictures` draws them with matplotlib (Agg), `report` makes one self-contained file of a scan,
`server` is the Starlette app and the uvicorn thread the agent starts. Nothing here is
imported on the scan or `process` path: the agent imports `server` only when `[web]` is on.
"""
