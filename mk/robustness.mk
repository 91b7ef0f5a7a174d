# Robustness grid on our plant (issue 14 item 7, docs/robustness.md): every controller of
# the study (the paper's four and the ablations) on mu x speed x mass x steering lag x
# manoeuvre, 96 cells and 576 runs in closed loop without CAN (studies/robustness_grid.py),
# on 2 worker processes. Each run is cached in build/robustness/ under a hash of its cell,
# controller and inputs (tuning, artefacts, paths, sources): an interrupted grid resumes,
# and a repeated one reruns only the runs whose inputs changed.
.PHONY: robustness robustness-smoke slalom-path

ROBUSTNESS_ARGS ?=

# 7.5 to 13 min on 2 cores from an empty cache (NMPC takes half of it); seconds when cached.
## robustness grid, every controller on mu x speed x mass x lag x manoeuvre -> results/robustness.{md,csv,png}
robustness: setup
	OPENBLAS_NUM_THREADS=1 $(PY) -m studies.robustness_grid --out results --workers 2 $(ROBUSTNESS_ARGS)
	$(PROVENANCE_STAMP) $(addprefix results/robustness.,md csv png) \
		--command "$(call provenance_command,robustness,ROBUSTNESS_ARGS)" \
		--inputs $(PROVENANCE_CLOSED_LOOP) $(PROVENANCE_DMDC) --modules studies.robustness_grid

## the robustness grid's smoke subset (LMPC, DKMPC x 2 cells) -> build/robustness-smoke/
robustness-smoke: setup
	OPENBLAS_NUM_THREADS=1 $(PY) -m studies.robustness_grid --quick --workers 2

## regenerate hil/paths/slalom.csv (the robustness grid's slalom) with python -m hil.path_files
slalom-path: setup
	$(PY) -m hil.path_files --path slalom
