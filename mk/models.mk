# Vehicle plant, baseline models and data set (models/): make data, make handling.
.PHONY: data handling data-coverage

DATA_DIR ?= data/nominal
DATA_HOURS ?= 2
DATA_SEED ?= 0

# The nominal data set for the Koopman training; generated only when missing (READY is
# written last, so an interrupted run is regenerated).
## generate the nominal training data set in DATA_DIR when missing
data: setup
	@if [ -f $(DATA_DIR)/READY ]; then echo "$(DATA_DIR) is up (delete it to regenerate)"; \
	else $(PY) -m models.data generate --out $(DATA_DIR) --hours $(DATA_HOURS) --seed $(DATA_SEED); fi

# Steady-state handling diagram (PNGs + JSON) and the parameter table, into results/.
## steady-state handling diagram and vehicle parameter table -> results/
handling: setup
	$(PY) -m studies.handling diagram --out results
	$(PY) -m studies.handling table > results/vehicle_params.md
	@echo "wrote results/vehicle_params.md"
	$(PROVENANCE_STAMP) results/handling.json results/handling_lateral_accel.png results/handling_yaw_gain.png \
		results/vehicle_params.md --command "make handling" \
		--inputs $(PROVENANCE_VEHICLE) --modules studies.handling

# Histograms of speed, grip use, steering, torque and mu of the training data sets:
# results/data_coverage.{png,md} (generates data/wide and data/nominal when missing).
## training data coverage plot (wide and nominal data sets) -> results/data_coverage.*
data-coverage: setup
	@test -f data/wide/READY || $(PY) -m models.data generate --out data/wide --profile wide --hours 2 --seed 0
	@test -f data/nominal/READY || $(PY) -m models.data generate --out data/nominal
	$(PY) -m studies.data_coverage --data data/wide data/nominal --out results
	$(PROVENANCE_STAMP) results/data_coverage.png results/data_coverage.md --command "make data-coverage" \
		--inputs $(PROVENANCE_VEHICLE) --modules studies.data_coverage models.data
