# Identification from the vehicle's own CAN logs (issue 20, docs/identification.md): the
# identification drive (a circuit with speed steps 3-30 m/s, studies/identification.py)
# and the study: a changed plant (mass +300 kg, rear tyres' cornering stiffness -20 %,
# steering lag x3) drives it with LMPC and
# an excitation over CAN, the Koopman model and the bicycle are trained from the recorded
# log alone, then Tables II/III run on the changed plant with nominal and identified models.
.PHONY: identify identification-drive

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

## regenerate the identification drive: hil/paths/identification.csv and hil/scenarios/identification/drive.toml
identification-drive: setup
	$(PY) -m studies.identification drive
