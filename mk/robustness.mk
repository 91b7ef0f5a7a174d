# Robustness grid on our plant (issue 14 item 7, docs/robustness.md): every controller of
# the study (the paper's four and the ablations) on mu x speed x mass x steering lag x
# manoeuvre, 96 cells and 576 runs in closed loop without CAN: the campaign grid
# studies/campaign/grids/robustness_closed_loop.toml on the campaign engine (runner
# closed_loop), 2 workers, then its report (studies/robustness_grid.py). Each run is cached
# in build/robustness/cache/ under a hash of its cell and the code: an interrupted grid
# resumes, and a repeated one reruns only the runs whose inputs changed.
.PHONY: robustness robustness-smoke slalom-path

ROBUSTNESS_ARGS ?=
ROBUSTNESS_CAMPAIGN := build/robustness
ROBUSTNESS_SMOKE_OUT := build/robustness-smoke

# 7.5 to 13 min on 2 cores from an empty cache (NMPC takes half of it); seconds when cached.
## robustness grid, every controller on mu x speed x mass x lag x manoeuvre -> results/robustness.{md,csv,png}
robustness: setup
	OPENBLAS_NUM_THREADS=1 $(PY) -m studies.campaign robustness_closed_loop --out $(ROBUSTNESS_CAMPAIGN) \
		--workers 2 $(ROBUSTNESS_ARGS)
	$(PY) -m studies.robustness_grid robustness_closed_loop --campaign $(ROBUSTNESS_CAMPAIGN) --out results
	$(PROVENANCE_STAMP) $(addprefix results/robustness.,md csv png) \
		--command "$(call provenance_command,robustness,ROBUSTNESS_ARGS)" \
		--inputs $(PROVENANCE_CLOSED_LOOP) $(PROVENANCE_DMDC) studies/campaign/grids/robustness_closed_loop.toml \
		--modules studies.campaign.__main__ studies.robustness_grid

## the robustness grid's smoke subset (LMPC, DKMPC x 2 cells) -> build/robustness-smoke/
robustness-smoke: setup
	OPENBLAS_NUM_THREADS=1 $(PY) -m studies.campaign robustness_closed_loop_smoke --out $(ROBUSTNESS_SMOKE_OUT) \
		--workers 2 $(ROBUSTNESS_ARGS)
	$(PY) -m studies.robustness_grid robustness_closed_loop_smoke --campaign $(ROBUSTNESS_SMOKE_OUT) \
		--out $(ROBUSTNESS_SMOKE_OUT)

## regenerate hil/paths/slalom.csv (the robustness grid's slalom) with python -m hil.path_files
slalom-path: setup
	$(PY) -m hil.path_files --path slalom
