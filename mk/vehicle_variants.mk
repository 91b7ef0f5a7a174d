# Vehicle variants the learned model never saw (issue 35 item 4, docs/vehicle-variants.md):
# each car of models/vehicle_variants.toml (a light car, a heavy car, a van, winter tyres)
# drives the two lane changes at high and low friction with every controller on the nominal
# models, is identified from its own CAN log as `make identify` does (drive over CAN with
# LMPC and prbs-torque, koopman_train --logs, the bicycle fit), and drives again with the
# identified models (studies/vehicle_variants.py).
.PHONY: vehicle-variants vehicle-variants-smoke

# e.g. VEHICLE_VARIANTS_ARGS='--variants van' or '--reuse-results' (resume) or '--reuse-log'.
VEHICLE_VARIANTS_ARGS ?=

# Per variant on 2 shared cores: the lane changes, the 612 s drive over CAN, the training
# (minutes, one torch thread) and the identified runs (docs/vehicle-variants.md has the
# measured times).
## vehicle variants: every controller on each car at high and low mu, nominal and identified models -> results/vehicle_variants.{md,json,png}
vehicle-variants: setup
	OPENBLAS_NUM_THREADS=1 $(PY) -m studies.vehicle_variants --out results $(VEHICLE_VARIANTS_ARGS)
	$(PROVENANCE_STAMP) $(addprefix results/vehicle_variants.,md json png) \
		--command "$(call provenance_command,vehicle-variants,VEHICLE_VARIANTS_ARGS)" \
		--inputs $(PROVENANCE_HIL) models/vehicle_variants.toml hil/scenarios/identification/drive.toml \
		--modules studies.vehicle_variants studies.vehicle_variants_report models.koopman_train

## the vehicle-variant study on tiny settings (one variant, 70 s drive, one epoch): checks the chain -> build/vehicle-variants-smoke/
vehicle-variants-smoke: setup
	OPENBLAS_NUM_THREADS=1 $(PY) -m studies.vehicle_variants --smoke --variants van \
		--out build/vehicle-variants-smoke --work build/vehicle-variants-smoke/work
