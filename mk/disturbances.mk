# Disturbance study (issue 35 item 2; docs/disturbances.md): every controller of the
# registry on the high-mu lane change and the straight-curve-straight path, without a
# disturbance and with each disturbance of docs/plant.md at two sizes, over CAN on the
# Python ECU (studies/campaign/grids/disturbances.toml, 182 cells with Stanley), on the
# campaign runner (local Ray, one worker per core; cached per cell in build/disturbances/,
# so a rerun computes only what changed). Then studies/disturbance_report.py writes
# results/disturbances.{md,csv,json,png}: e_Y RMSE and the steady lateral offsets on the
# straights.
#   make disturbances-smoke   4 cells (ESO-DKMPC, LMPC x straight_curve x none, a 0.02 rad
#                             steering offset) -> build/disturbances-smoke/
#   DISTURBANCES_ARGS="--workers 2" or "--address 127.0.0.1:6379" (an existing Ray cluster)
.PHONY: disturbances disturbances-smoke

DISTURBANCES_ARGS ?=
DISTURBANCES_CAMPAIGN := build/disturbances
DISTURBANCES_SMOKE_OUT := build/disturbances-smoke

## disturbance study, every controller x {lane change, straight-curve-straight} x disturbances -> results/disturbances.*
disturbances: setup
	$(PY) -m studies.campaign disturbances --out $(DISTURBANCES_CAMPAIGN) $(DISTURBANCES_ARGS)
	$(PY) -m studies.disturbance_report disturbances --campaign $(DISTURBANCES_CAMPAIGN) --out results
	$(PROVENANCE_STAMP) $(addprefix results/disturbances.,md csv json png) \
		--command "$(call provenance_command,disturbances,DISTURBANCES_ARGS)" \
		--inputs $(PROVENANCE_HIL) $(PROVENANCE_DMDC) studies/campaign/grids/disturbances.toml \
		--modules studies.campaign.__main__ studies.disturbance_report

## the disturbance study's smoke subset (4 cells) -> build/disturbances-smoke/
disturbances-smoke: setup
	$(PY) -m studies.campaign disturbances_smoke --out $(DISTURBANCES_SMOKE_OUT) $(DISTURBANCES_ARGS)
	$(PY) -m studies.disturbance_report disturbances_smoke --campaign $(DISTURBANCES_SMOKE_OUT) \
		--out $(DISTURBANCES_SMOKE_OUT)
