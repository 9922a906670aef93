"""The grid library (as grid_map_core is): the grid over a region, the height map, box and
extreme filters, masked smoothing, polygon geometry and volume integration. Pure numpy; it
imports only `silo_agent.base`, and reconstruct, detect, live and calibrate all build on it."""
