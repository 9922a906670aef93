"""Live mode: a height map updated from the newest depth frames for leveling robots.

`map` is the pure core (frames -> per-cell running heights, robot kept out, changed cells);
`session` is the shell that captures, publishes and keeps time.
"""
