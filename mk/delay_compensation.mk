# The steering QP's optional actuator terms (issue 37; studies/delay_compensation.py,
# docs/tuning.md): ESO-DKMPC, DKMPC and LMPC with the steer-rate rows and the delay
# compensation off / on, on the two lane changes of Tables II-III, with the steering lag
# nominal, x3 and a slow servo and a command dead time of 0, 10 and 25 ms. Closed loop
# without CAN: 216 runs, about 4 min on 2 cores.
.PHONY: delay-compensation
## steer-rate rows and delay compensation on the lane changes, lag x3 and slow servo -> results/delay_compensation.* (~4 min)
delay-compensation: setup
	OPENBLAS_NUM_THREADS=1 $(PY) -m studies.delay_compensation --out results
	$(PROVENANCE_STAMP) $(addprefix results/delay_compensation.,md json) --command "make delay-compensation" \
		--inputs $(PROVENANCE_CLOSED_LOOP) --modules studies.delay_compensation
