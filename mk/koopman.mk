# Deep Koopman model (issue 4): training of the default artefact and Table I.
.PHONY: train table1 table1-lsq test-koopman model-fidelity dmdc seed-spread step-steer-spread lateral-regimes

KOOPMAN_DATA ?= data/nominal
# The default artefact's data: the wide profile (3-35 m/s, mu 0.3-1.0, into saturation).
TRAIN_DATA ?= data/wide
KOOPMAN_ARTIFACT := models/artifacts/dk_d5

# The default artefact's form (issue 14, item 4): the mirror-symmetric lift with d = 8 learned
# features (2 even), the steering servo's lag in the state, the steer-bilinear term N(v) and the
# gain anchor (weight 10); Table I's row "mirror-symmetric steer-bilinear + gain anchor (w = 10)".
# See docs/koopman.md, "The default model".
KOOPMAN_FORM ?= --features 8 --mirror-symmetric --even-features 2 --servo-lag --steer-bilinear --gain-anchor 10

# Generates the wide data set when missing (2 h, seed 0), then trains the default model and
# writes models/artifacts/dk_d5.{npz,json}. The committed artefact's test errors are kept in
# build/ and compared (within 10 %) when its training settings are the same. 6.8 min here
# (2026-12-03, one torch thread, 2 cores; the early stop decides: 28 epochs for seed 0).
## train the default deep Koopman model (anchored mirror form, wide data) -> models/artifacts/dk_d5.{npz,json}
train: setup
	@test -f $(TRAIN_DATA)/READY || $(PY) -m models.data generate --out $(TRAIN_DATA) --profile wide --hours 2 --seed 0
	@mkdir -p build
	@if [ -f $(KOOPMAN_ARTIFACT).json ]; then cp $(KOOPMAN_ARTIFACT).json build/dk_d5.previous.json; fi
	$(PY) -m models.koopman_train --data $(TRAIN_DATA) --out $(KOOPMAN_ARTIFACT) --replace $(KOOPMAN_FORM) \
		$$( [ -f build/dk_d5.previous.json ] && echo --compare-with build/dk_d5.previous.json ) $(TRAIN_ARGS)

# Table I (9 learned forms x 5 seeds + DMDc, EDMDc, edmdc-linear / -bilinear, bicycle, single track on the wide data):
# results/table1.md, results/table1.json, results/fig6_prediction_errors.png,
# results/prediction_horizon_rmse.png. Rows and seeds: the grid studies/campaign/grids/table1.toml,
# each row x seed a cell of the campaign engine; trained models and measured cells are cached in
# build/table1/ (the default row's seed 0 reuses the committed artefact when it matches). About 1.5 h on the
# first hosts; 39 min on the Intel Xeon one of 2026-12-06 (35 trainings on 2 Ray workers).
## Table I: learned forms over 5 seeds and the physics models -> results/table1.*
table1: setup
	@test -f $(TRAIN_DATA)/READY || $(PY) -m models.data generate --out $(TRAIN_DATA) --profile wide --hours 2 --seed 0
	$(PY) -m studies.table1 --data $(TRAIN_DATA)
	$(PROVENANCE_STAMP) results/table1.md results/table1.json results/fig6_prediction_errors.png \
		results/prediction_horizon_rmse.png --command "$(call provenance_command,table1,TRAIN_DATA)" \
		--inputs $(PROVENANCE_VEHICLE) $(PROVENANCE_ARTEFACT) --modules studies.table1 models.data

# Table I's rows without training (DMDc, EDMDc, the trainer's edmdc-linear / edmdc-bilinear,
# the bicycle, the single track) over its 5 seeds and split, and the best least-squares row
# beside the default deep row of results/table1.json: results/table1_least_squares.{md,json}.
# 20 s on 2 cores once the data set exists (2026-12-05).
## Table I's least-squares and physics rows, no training (20 s) -> results/table1_least_squares.*
table1-lsq: setup
	@test -f $(TRAIN_DATA)/READY || $(PY) -m models.data generate --out $(TRAIN_DATA) --profile wide --hours 2 --seed 0
	$(PY) -m studies.table1_least_squares --data $(TRAIN_DATA)
	$(PROVENANCE_STAMP) results/table1_least_squares.md results/table1_least_squares.json \
		--command "$(call provenance_command,table1-lsq,TRAIN_DATA)" \
		--inputs $(PROVENANCE_VEHICLE) results/table1.json --modules studies.table1_least_squares models.data

## tests of the Koopman model, its training and the baselines
test-koopman: setup
	$(PY) -m pytest -q tests/test_koopman.py tests/test_koopman_train.py tests/test_koopman_synthetic.py tests/test_koopman_baselines.py

# Step steer at 10-25 m/s and 1 s / 2 s open-loop RMSE of the default learned model, the
# paper's form, LMPC's bicycle and NMPC's single track: results/model_fidelity.{md,json}.
## model fidelity: step steer and open-loop RMSE vs the physics models -> results/model_fidelity.*
model-fidelity: setup
	@test -f $(TRAIN_DATA)/READY || $(PY) -m models.data generate --out $(TRAIN_DATA) --profile wide --hours 2 --seed 0
	$(PY) -m studies.model_fidelity --data $(TRAIN_DATA) --out results
	$(PROVENANCE_STAMP) results/model_fidelity.md results/model_fidelity.json --command "make model-fidelity" \
		--inputs $(PROVENANCE_VEHICLE) $(PROVENANCE_ARTEFACT) --modules studies.model_fidelity

# Step steer of the default training and three variants (small-signal weighting; one wheel-angle
# row for all speeds; the mirror-symmetric form) over the 5 seeds of Table I: is the step-steer error a bias or the
# seed? results/step_steer_spread.{md,json,png}. Shares Table I's cache (build/table1/);
# about 20 min on 2 cores when nothing is cached (19 trainings on 2 Ray workers, 2026-12-02).
## step steer over 5 seeds, default training and three variants -> results/step_steer_spread.*
step-steer-spread: setup
	@test -f $(TRAIN_DATA)/READY || $(PY) -m models.data generate --out $(TRAIN_DATA) --profile wide --hours 2 --seed 0
	$(PY) -m studies.step_steer_spread --data $(TRAIN_DATA)
	$(PROVENANCE_STAMP) $(addprefix results/step_steer_spread.,md json png) \
		--command "$(call provenance_command,step-steer-spread,TRAIN_DATA)" \
		--inputs $(PROVENANCE_VEHICLE) $(PROVENANCE_ARTEFACT) --modules studies.step_steer_spread models.data

# Why the learned step steer is low at 10-15 m/s: local least-squares fits of the lateral
# dynamics on the default artefact's training runs, per speed and per longitudinal / lateral
# regime, driven by the plant's step steer: results/lateral_regimes.{md,json,png}. Seconds.
## the small-signal yaw gain the data hold, by regime -> results/lateral_regimes.*
lateral-regimes: setup
	@test -f $(TRAIN_DATA)/READY || $(PY) -m models.data generate --out $(TRAIN_DATA) --profile wide --hours 2 --seed 0
	$(PY) -m studies.lateral_regimes --data $(TRAIN_DATA)
	$(PROVENANCE_STAMP) $(addprefix results/lateral_regimes.,md json png) \
		--command "$(call provenance_command,lateral-regimes,TRAIN_DATA)" \
		--inputs $(PROVENANCE_VEHICLE) $(PROVENANCE_ARTEFACT) --modules studies.lateral_regimes models.data

# The DMDc model of the dmdc-eso ablation (ESO-DKMPC with no lift): least squares on the
# training runs of the default artefact's data and split (its JSON's data_dir and split),
# committed as models/artifacts/dmdc.{npz,json} so the ECU needs no data. A few seconds
# once the data set exists. See docs/controllers.md, "Ablations".
## fit the dmdc-eso ablation's DMDc model on dk_d5's training runs -> models/artifacts/dmdc.{npz,json}
dmdc: setup
	@test -f $(TRAIN_DATA)/READY || $(PY) -m models.data generate --out $(TRAIN_DATA) --profile wide --hours 2 --seed 0
	$(PY) -m models.dmdc_artifact --data $(TRAIN_DATA) --out models/artifacts/dmdc --replace

# make table1 when build/table1/ lacks a seed model that make seed-spread reads (a fresh
# clone: 39 min of training on 2 cores), else nothing: make after-tuning's step before it.
.PHONY: seed-spread-models
## make table1's seed models for make seed-spread, trained only if build/table1/ lacks one
seed-spread-models: setup
	@$(PY) -m studies.seed_spread --check-models || $(MAKE) --no-print-directory table1

# Tables II / III with the learned controllers once per seed of the default model (seeds
# 1-4 come from make table1's cache): results/seed_spread.{md,json}.
## Tables II/III over the 5 seeds of the learned model -> results/seed_spread.*
seed-spread: setup
	$(PY) -m studies.seed_spread --out results
	$(PROVENANCE_STAMP) results/seed_spread.md results/seed_spread.json --command "make seed-spread" \
		--inputs $(PROVENANCE_CLOSED_LOOP) --modules studies.seed_spread
