"""Simulated user studies: many closed-loop trials, in parallel, with tables and figures.

- `course`: thesis Table 6.3 — N simulated users (seeded `UserProfile`s, the same users
  in every cell) on the obstacle course per controller × localizer × surface;
  collisions front / side / rear-wheel and their change against the manual baseline.
- `corner`: thesis Figs 6.5–6.8 — controller parameter sweeps on the `corner` course
  with a user pushing straight at constant force; individual and averaged paths.

`trial` runs one simulated trial (the unit of work), `engine` runs many of them on the
local cores or on a Ray cluster, `settings` parses `NAME.FIELD=VALUE` config overrides,
`store` writes the results database and CSV, `tables` the statistics and Markdown
tables, `figures` the path figures.
"""
