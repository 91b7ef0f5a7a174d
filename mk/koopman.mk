# Deep Koopman model (issue 4): training of the default artefact and Table I.
.PHONY: train table1 test-koopman

KOOPMAN_DATA ?= data/nominal
KOOPMAN_ARTIFACT := models/artifacts/dk_d5

# Generates the nominal data set when missing (the generator's defaults: 2 h, seed 0, the
# same as `make data`), then trains d = 5 and writes models/artifacts/dk_d5.{npz,json}.
# The committed artefact's test errors are kept in build/ and compared (within 10 %).
## train the deep Koopman model d = 5 -> models/artifacts/dk_d5.{npz,json}
train: setup
	@test -f $(KOOPMAN_DATA)/READY || $(PY) -m models.data generate --out $(KOOPMAN_DATA)
	@mkdir -p build
	@if [ -f $(KOOPMAN_ARTIFACT).json ]; then cp $(KOOPMAN_ARTIFACT).json build/dk_d5.previous.json; fi
	$(PY) -m models.koopman_train --data $(KOOPMAN_DATA) --out $(KOOPMAN_ARTIFACT) \
		$$( [ -f build/dk_d5.previous.json ] && echo --compare-with build/dk_d5.previous.json ) $(TRAIN_ARGS)

# Table I (d = 2, 3, 5, 10, 15 + DMDc + EDMDc): results/table1.md, results/table1.json,
# results/fig6_prediction_errors.png, results/prediction_horizon_rmse.png. Trained models
# are cached in build/table1/ (d = 5 reuses the committed artefact when it matches).
## Table I: lifted dimensions and DMDc/EDMDc baselines -> results/table1.*
table1: setup
	@test -f $(KOOPMAN_DATA)/READY || $(PY) -m models.data generate --out $(KOOPMAN_DATA)
	$(PY) -m studies.table1 --data $(KOOPMAN_DATA)
	$(PROVENANCE_STAMP) results/table1.md results/table1.json results/fig6_prediction_errors.png \
		results/prediction_horizon_rmse.png --command "$(call provenance_command,table1,KOOPMAN_DATA)" \
		--inputs $(PROVENANCE_VEHICLE) $(PROVENANCE_ARTEFACT) --modules studies.table1 models.data

## tests of the Koopman model, its training and the baselines
test-koopman: setup
	$(PY) -m pytest -q tests/test_koopman.py tests/test_koopman_train.py tests/test_koopman_synthetic.py tests/test_koopman_baselines.py
