# Weights against road (studies/weight_tradeoff.py; docs/tuning.md): every controller's
# Table II and Table III e_Y RMSE over the tuning sweep's 36 weight settings. An analysis of
# the evaluation scenarios, never a tuning: it chooses and writes nothing but its report.
# About 10 min with 2 workers on 2 cores (NMPC takes most of it).
.PHONY: tradeoff

TRADEOFF_ARGS ?=

## Table II vs Table III e_Y over the weight grid, per controller -> results/weight_tradeoff.* (~10 min)
tradeoff: setup
	OPENBLAS_NUM_THREADS=1 $(PY) -m studies.weight_tradeoff --out results --workers 2 $(TRADEOFF_ARGS)
	$(PROVENANCE_STAMP) $(addprefix results/weight_tradeoff.,md json png) \
		--command "$(call provenance_command,tradeoff,TRADEOFF_ARGS)" \
		--inputs $(PROVENANCE_CLOSED_LOOP) $(PROVENANCE_DMDC) --modules studies.weight_tradeoff
