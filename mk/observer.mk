# The observer stage of the tuning procedure on the tuning set with disturbances added
# (issue 35; studies/observer_tuning.py, docs/tuning.md): the observer fields of ESO-DKMPC,
# LMPC-ESO and DMDc-ESO over a grid, every other field at the tuning file's value, on the 8
# tuning manoeuvres and 3 steady drives, and the same 11 with one constant disturbance each.
# Writes the chosen observer fields into controller/tuning.toml. About 50 min with 2 workers
# on 2 cores.
.PHONY: tune-observer

TUNE_OBSERVER_ARGS ?=
## tune the observers on the tuning set + disturbances -> controller/tuning.toml, results/observer_tuning.* (~50 min)
tune-observer: setup
	OPENBLAS_NUM_THREADS=1 $(PY) -m studies.observer_tuning --out results --workers 2 $(TUNE_OBSERVER_ARGS)
	$(PROVENANCE_STAMP) $(addprefix results/observer_tuning.,md json) \
		--command "$(call provenance_command,tune-observer,TUNE_OBSERVER_ARGS)" \
		--inputs $(PROVENANCE_VEHICLE) $(PROVENANCE_ARTEFACT) $(PROVENANCE_DMDC) \
		$(PROVENANCE_TUNING_SET) --modules studies.observer_tuning models.disturbance

# The refinement right after tune-observer (studies/observer_tuning.py --stage refine): the
# innovation bound's widening while the innovation keeps its sign, and a finer grid of the
# yaw-rate bias pole, for the same three controllers on the same 22 runs, every other field
# at the tuning file's value. About 12 min with 2 workers on 2 cores.
.PHONY: tune-observer-refine
TUNE_OBSERVER_REFINE_ARGS ?=
## refine the observers (innovation bound's widening, bias pole) on the tuning set + disturbances -> controller/tuning.toml, results/observer_tuning_refine.* (~12 min)
tune-observer-refine: setup
	OPENBLAS_NUM_THREADS=1 $(PY) -m studies.observer_tuning --stage refine --out results --workers 2 $(TUNE_OBSERVER_REFINE_ARGS)
	$(PROVENANCE_STAMP) $(addprefix results/observer_tuning_refine.,md json) \
		--command "$(call provenance_command,tune-observer-refine,TUNE_OBSERVER_REFINE_ARGS)" \
		--inputs $(PROVENANCE_VEHICLE) $(PROVENANCE_ARTEFACT) $(PROVENANCE_DMDC) \
		$(PROVENANCE_TUNING_SET) --modules studies.observer_tuning models.disturbance

# The observer's design choices against variants that each change one (docs/eso.md): about
# 1 min on 2 cores (30 closed-loop runs without CAN).
.PHONY: observer-variants
## ESO-DKMPC against one-change variants of its observer (and DKMPC) -> results/observer_variants.md (~1 min)
observer-variants: setup
	OPENBLAS_NUM_THREADS=1 $(PY) -m studies.observer_variants --out results
	$(PROVENANCE_STAMP) results/observer_variants.md --command "make observer-variants" \
		--inputs $(PROVENANCE_CLOSED_LOOP) --modules studies.observer_variants

# The observer's slow pole against the robustness grid's mismatch cells and the tuning set's
# objective (studies/observer_speed.py, docs/eso.md): the campaign grid observer_speed (480
# closed-loop runs, cached in build/observer_speed/), the observer stage's 22 runs at each
# pole, and its 11 undisturbed runs on two changed plants (+150 kg, steering lag x2) at each
# pole and for DKMPC. About 9 min on 2 cores when nothing is cached.
.PHONY: observer-speed
OBSERVER_SPEED_CAMPAIGN := build/observer_speed
## ESO-DKMPC at four slow observer poles: mismatch cells against DKMPC, tuning set objective, changed plants -> results/observer_speed.* (~9 min)
observer-speed: setup
	OPENBLAS_NUM_THREADS=1 $(PY) -m studies.campaign observer_speed --out $(OBSERVER_SPEED_CAMPAIGN) --workers 2 --no-progress
	OPENBLAS_NUM_THREADS=1 $(PY) -m studies.observer_speed --campaign $(OBSERVER_SPEED_CAMPAIGN) --out results --no-progress
	$(PROVENANCE_STAMP) $(addprefix results/observer_speed.,md json png) --command "make observer-speed" \
		--inputs $(PROVENANCE_CLOSED_LOOP) $(PROVENANCE_TUNING_SET) studies/campaign/grids/observer_speed.toml \
		--modules studies.campaign.__main__ studies.observer_speed models.disturbance

# The second observer stage (studies/observer_tuning.py --stage slip-target): the bound and
# the fade of the heading target's steady side slip (controller/steady_slip.py) for every
# MPC on the observer stage's 22 runs, every other field at the tuning file's value (so
# after tune-observer and tune-observer-refine). About 25 min with 2 workers on 2 cores.
.PHONY: tune-slip-target
TUNE_SLIP_TARGET_ARGS ?=
## tune the heading target's side slip on the tuning set + disturbances -> controller/tuning.toml, results/observer_tuning_slip_target.* (~25 min)
tune-slip-target: setup
	OPENBLAS_NUM_THREADS=1 $(PY) -m studies.observer_tuning --stage slip-target --out results --workers 2 $(TUNE_SLIP_TARGET_ARGS)
	$(PROVENANCE_STAMP) $(addprefix results/observer_tuning_slip_target.,md json) \
		--command "$(call provenance_command,tune-slip-target,TUNE_SLIP_TARGET_ARGS)" \
		--inputs $(PROVENANCE_VEHICLE) $(PROVENANCE_ARTEFACT) $(PROVENANCE_DMDC) \
		$(PROVENANCE_TUNING_SET) --modules studies.observer_tuning models.disturbance
