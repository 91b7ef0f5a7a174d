# The MPCs' grip envelope (studies/grip_envelope.py, docs/grip-envelope.md), the tuning
# procedure's last stage: each MPC (the QP MPCs and NMPC) at grip_slip_excess off, 2 to 6
# degrees on the tuning set with disturbances and a limit set (its undisturbed manoeuvres
# with the rear tyres x0.65, and with that +150 kg and the steering's lag x2); then, for each
# MPC the stage switches on, the margin, the recovery and the peak memory one at a time on
# the same runs; then Tables II / III's lane changes on the nominal and make identify's
# changed plant, Stanley beside them. Writes each MPC's four grip fields into
# controller/tuning.toml. Closed loop without CAN: about 3600 runs, about 50 min on 2 cores
# (NMPC takes most of it). As the other tuning stages, its stamp leaves out the tuning file
# it writes.
.PHONY: grip-envelope
## tune the grip envelope on the tuning set + limit set -> controller/tuning.toml, results/grip_envelope.* (~50 min)
grip-envelope: setup
	OPENBLAS_NUM_THREADS=1 $(PY) -m studies.grip_envelope --out results --workers 2
	$(PROVENANCE_STAMP) $(addprefix results/grip_envelope.,md json png) --command "make grip-envelope" \
		--inputs $(PROVENANCE_VEHICLE) $(PROVENANCE_ARTEFACT) $(PROVENANCE_SCENARIOS) $(PROVENANCE_PATHS) \
		$(PROVENANCE_DMDC) $(PROVENANCE_TUNING_SET) \
		--modules studies.grip_envelope studies.identification controller.grip_envelope models.disturbance hil.fault_injector

# The margin's effect on make identify's changed plant (a sensitivity study: it chooses
# nothing): every QP MPC at grip_margin 0 to 0.2 and the file's value, NMPC beside them, on
# the low-mu lane change with the nominal models (studies/campaign/grids/grip_margin.toml).
# Closed loop without CAN, 31 runs, about 1 min on 2 cores.
.PHONY: grip-margin
GRIP_MARGIN_OUT := results/grip_margin
## the grip envelope's margin on the changed plant's low-mu lane change, every QP MPC -> results/grip_margin/ (~1 min)
grip-margin: setup
	OPENBLAS_NUM_THREADS=1 $(PY) -m studies.campaign grip_margin --out $(GRIP_MARGIN_OUT) --workers 2 --no-progress
	$(PROVENANCE_STAMP) $(addprefix $(GRIP_MARGIN_OUT)/,cells.csv summary.md heatmap_e_y_rmse.png) \
		--command "make grip-margin" \
		--inputs $(PROVENANCE_CLOSED_LOOP) $(PROVENANCE_DMDC) studies/campaign/grids/grip_margin.toml \
		--modules studies.campaign.__main__ hil.fault_injector
