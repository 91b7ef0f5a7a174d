# Tuning on a tuning set disjoint from the evaluation (issue 14, item 5; docs/tuning.md):
# one procedure for every registered controller (studies/tuning_sweep.py) on the smooth
# random paths of hil/scenarios/tuning/ (studies/tuning_set.py), never on the double lane
# changes of Tables II/III. Writes the chosen values into controller/tuning.toml. Its runs are
# cells of the campaign grid studies/campaign/grids/tuning_sweep.toml (one tuning override
# per setting), cached in build/tuning_sweep/cache/: an interrupted make tune resumes.
.PHONY: tune tuning-set

TUNE_ARGS ?=
# The tuning set's files (beside, not among, PROVENANCE_SCENARIOS / PROVENANCE_PATHS).
PROVENANCE_TUNING_SET := $(sort $(wildcard hil/scenarios/tuning/*.toml)) $(sort $(wildcard hil/paths/tuning/*.csv))

# About 50 min with 2 workers on 2 cores (8 tuning scenarios of 10 s; NMPC takes most of it);
# TUNE_ARGS="--reuse results/tuning_sweep.json" runs only the settings not stored there.
# Then regenerate the evaluation with the tuned values: make tables run.
## tune every controller on the tuning set -> controller/tuning.toml, results/tuning_sweep.* (~50 min)
tune: setup
	OPENBLAS_NUM_THREADS=1 $(PY) -m studies.tuning_sweep --out results --workers 2 $(TUNE_ARGS)
	$(PROVENANCE_STAMP) $(addprefix results/tuning_sweep.,md json png) \
		--command "$(call provenance_command,tune,TUNE_ARGS)" \
		--inputs $(PROVENANCE_VEHICLE) $(PROVENANCE_TUNING) $(PROVENANCE_ARTEFACT) $(PROVENANCE_DMDC) \
		$(PROVENANCE_TUNING_SET) studies/campaign/grids/tuning_sweep.toml --modules studies.tuning_sweep

# The tuning set's paths and scenarios from their seeds (committed; a test checks they match).
## regenerate the tuning set hil/paths/tuning/*.csv, hil/scenarios/tuning/*.toml from its seeds
tuning-set: setup
	$(PY) -m studies.tuning_set
