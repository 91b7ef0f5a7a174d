# The MPCs' grip envelope (studies/grip_envelope.py, docs/grip-envelope.md): each MPC (the QP
# MPCs and NMPC) at grip_slip_excess off, 2 to 6 degrees on the tuning set with disturbances and
# on its undisturbed manoeuvres with the rear tyres x0.65 (the procedure's objective and choice),
# then on Tables II / III's lane changes on the nominal and make identify's changed plant, Stanley
# beside them. Closed loop without CAN: 1352 runs, about 21 min on 2 cores (NMPC takes most of
# it). Writes no tuning file.
.PHONY: grip-envelope
## the grip envelope's tuning-stage choice and the lane changes on the changed plant -> results/grip_envelope.* (~21 min)
grip-envelope: setup
	OPENBLAS_NUM_THREADS=1 $(PY) -m studies.grip_envelope --out results --workers 2
	$(PROVENANCE_STAMP) $(addprefix results/grip_envelope.,md json png) --command "make grip-envelope" \
		--inputs $(PROVENANCE_CLOSED_LOOP) $(PROVENANCE_DMDC) $(PROVENANCE_TUNING_SET) \
		--modules studies.grip_envelope studies.identification controller.grip_envelope models.disturbance hil.fault_injector
