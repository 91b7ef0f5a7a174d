# The observer stage of the tuning procedure on the tuning set with disturbances added
# (issue 35; studies/observer_tuning.py, docs/tuning.md): the observer fields of ESO-DKMPC,
# LMPC-ESO and DMDc-ESO over a grid, every other field at the tuning file's value, on the 8
# tuning manoeuvres and the same 8 with one constant disturbance each. Writes the chosen
# observer fields into controller/tuning.toml. About 35 min with 2 workers on 2 cores.
.PHONY: tune-observer

TUNE_OBSERVER_ARGS ?=
## tune the observers on the tuning set + disturbances -> controller/tuning.toml, results/observer_tuning.* (~35 min)
tune-observer: setup
	OPENBLAS_NUM_THREADS=1 $(PY) -m studies.observer_tuning --out results --workers 2 $(TUNE_OBSERVER_ARGS)
	$(PROVENANCE_STAMP) $(addprefix results/observer_tuning.,md json) \
		--command "$(call provenance_command,tune-observer,TUNE_OBSERVER_ARGS)" \
		--inputs $(PROVENANCE_VEHICLE) $(PROVENANCE_ARTEFACT) $(PROVENANCE_DMDC) \
		$(PROVENANCE_TUNING_SET) --modules studies.observer_tuning models.disturbance
