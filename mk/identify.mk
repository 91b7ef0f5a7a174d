# Identification from the vehicle's own CAN logs (issue 20, docs/identification.md): the
# identification drive (a circuit with speed steps 3-30 m/s, studies/identification.py)
# and the study: a changed plant (mass +300 kg, rear tyres' cornering stiffness -20 %,
# steering lag x3) drives it with LMPC and
# an excitation over CAN, the Koopman model and the bicycle are trained from the recorded
# log alone, then Tables II/III run on the changed plant with nominal and identified models.
.PHONY: identify identify-lsq identification-drive

IDENTIFY_ARGS ?=

# 4-9 min measured on 2 shared cores (4.3 min at load ~2.5): the 612 s drive over CAN
# (1.5-3 min), the training (2-7 min, one torch thread), 24 closed-loop runs (10-20 s).
# --reuse-log skips the drive.
## identification study: drive the changed plant, train from its CAN log, Tables II/III with nominal and identified models -> results/identification/
identify: setup
	OPENBLAS_NUM_THREADS=1 $(PY) -m studies.identification study --out results/identification $(IDENTIFY_ARGS)
	$(PROVENANCE_STAMP) $(addprefix results/identification/,tables.md summary.json training_report.md) \
		--command "$(call provenance_command,identify,IDENTIFY_ARGS)" \
		--inputs $(PROVENANCE_HIL) hil/scenarios/identification/drive.toml \
		--modules studies.identification models.koopman_train

# Issue 40, item 3 on the identification log: the deep model trained as `make identify` trains
# it, seeds 0-4 (2-7 min each on one core, cached in build/identification_lsq/ by seed and
# settings), beside the least-squares lifts edmdc-linear / edmdc-bilinear on the same test pieces.
IDENTIFY_LOG := build/identification/drive_changed.log
IDENTIFY_LSQ_ARGS ?=

## deep model (5 seeds) vs least-squares lifts on make identify's log: 1 s / 2 s open-loop RMSE -> results/identification/least_squares.{md,json}
identify-lsq: setup
	@test -f $(IDENTIFY_LOG) || { echo "error: $(IDENTIFY_LOG) not found: run make identify first (it records the drive's log)" >&2; exit 2; }
	OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 MKL_NUM_THREADS=1 $(PY) -m studies.identification_least_squares \
		--log $(IDENTIFY_LOG) --vehicle build/identification/vehicle_changed.toml --out results/identification $(IDENTIFY_LSQ_ARGS)
	$(PROVENANCE_STAMP) results/identification/least_squares.md results/identification/least_squares.json \
		--command "$(call provenance_command,identify-lsq,IDENTIFY_LSQ_ARGS)" \
		--inputs $(PROVENANCE_HIL) hil/scenarios/identification/drive.toml \
		--modules studies.identification_least_squares models.koopman_train models.lifted_least_squares

## regenerate the identification drive: hil/paths/identification.csv and hil/scenarios/identification/drive.toml
identification-drive: setup
	$(PY) -m studies.identification drive
