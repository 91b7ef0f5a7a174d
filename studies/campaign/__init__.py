"""Campaigns: a grid of runs (controller x scenario x mu x speed x mass x steering lag x
fault x model x seed, minus exclusions) on Ray, each cell one lockstep HIL run over the
virtual bus through the same session code as ``python -m hil run``.

``python -m studies.campaign GRID.toml --out DIR [--address ADDR] [--workers N]``;
``make campaign-smoke``, ``make campaign``; manual: ``docs/campaign.md``.

- `grid`: grid files, expansion, a cell as a scenario file;
- `cell`: one cell's run (what a worker executes); `closed_loop_cell` without CAN;
- `tuning_override`: the ``tuning`` axis (a cell's controller with tuning fields replaced:
  ``make tune``'s settings, grid ``tuning_sweep``);
- `prediction_grid`, `prediction_cell`, `prediction_rows`, `prediction_training`: the
  ``prediction`` runner (Table I, ``make table1``: a model row x a seed, trained or fitted,
  its open-loop prediction errors measured; grids ``table1``, ``table1_smoke``);
- `runner`: cache keys, the cache, the Ray and serial executors, the campaign loop;
- `report`: cells.csv, summary.md, heat maps;
- `__main__`: the command line.
"""
