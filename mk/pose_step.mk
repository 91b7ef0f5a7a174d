# The QP MPCs' pose step (studies/pose_step.py, docs/controllers.md "The pose step"): eq. 20's
# explicit Euler against the midpoint heading (pose_heading_advance 0 / 0.5), every other
# field at the tuning file's value, on the tuning set with disturbances and on the study
# scenarios. Closed loop without CAN: 263 runs, about 10 min on 2 cores. Writes no tuning file.
.PHONY: pose-step
## eq. 20's pose step against the midpoint heading on the tuning set and the study scenarios -> results/pose_step.* (~10 min)
pose-step: setup
	OPENBLAS_NUM_THREADS=1 $(PY) -m studies.pose_step --out results --workers 2
	$(PROVENANCE_STAMP) $(addprefix results/pose_step.,md json png) --command "make pose-step" \
		--inputs $(PROVENANCE_CLOSED_LOOP) $(PROVENANCE_DMDC) $(PROVENANCE_TUNING_SET) \
		--modules studies.pose_step models.disturbance
