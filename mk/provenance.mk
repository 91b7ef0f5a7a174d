# Provenance of results/ (studies/provenance.py): each target that writes results files
# stamps them afterwards in results/PROVENANCE.json with its command, the commit (-dirty
# when the tree was) and a hash of its data inputs and the source files of its modules.
# `make provenance` lists the stale ones with the command that regenerates each; long
# studies not rerun since their inputs changed are listed in results/KNOWN_STALE.md.
.PHONY: provenance restamp

PROVENANCE_STAMP = $(PY) -m studies.provenance stamp
# `make NAME` plus the values of the variables $(2) that change what NAME computes.
provenance_command = $(strip make $(1) $(foreach v,$(2),$(if $(strip $($(v))),$(v)='$(strip $($(v)))')))

# The data files the studies read.
PROVENANCE_VEHICLE := models/vehicle.toml
PROVENANCE_TUNING := controller/tuning.toml
PROVENANCE_ARTEFACT := models/artifacts/dk_d5.npz models/artifacts/dk_d5.json models/artifacts/dk_paper_nominal.npz models/artifacts/dk_paper_nominal.json
# The dmdc-eso ablation's model (make dmdc), an input of the study with the ablations.
PROVENANCE_DMDC := models/artifacts/dmdc.npz models/artifacts/dmdc.json
PROVENANCE_SCENARIOS := $(sort $(wildcard hil/scenarios/*.toml))
PROVENANCE_PATHS := $(sort $(wildcard hil/paths/*.csv))
PROVENANCE_DBC := can_defs/vehicle.dbc
# A closed-loop study without CAN, and one over CAN.
PROVENANCE_CLOSED_LOOP := $(PROVENANCE_VEHICLE) $(PROVENANCE_TUNING) $(PROVENANCE_ARTEFACT) \
	$(PROVENANCE_SCENARIOS) $(PROVENANCE_PATHS)
PROVENANCE_HIL := $(PROVENANCE_CLOSED_LOOP) $(PROVENANCE_DBC)

## list stale results files (inputs changed since their stamp) with their commands
provenance: setup
	$(PY) -m studies.provenance check

# A product-code change that keeps behaviour: restamp the stale studies on the proof of a
# smoke subset run at BASE and here (studies/restamp.py; docs/architecture.md).
# RESTAMP_EXCLUDE: globs of results files to leave stale (a path the smoke does not run).
BASE ?=
RESTAMP_EXCLUDE ?=
## restamp results made stale by a behaviour-keeping code change: make restamp BASE=REV
restamp: setup firmware
	@if [ -z "$(BASE)" ]; then echo "error: make restamp needs BASE=REV (the commit at which the stale files were current)" >&2; exit 2; fi
	$(PY) -m studies.restamp --base $(BASE) $(foreach glob,$(RESTAMP_EXCLUDE),--exclude '$(glob)')
