# Campaigns on Ray (studies/campaign, docs/campaign.md): a grid of lockstep HIL runs over
# the virtual bus, one cell per run, cached per cell in the output folder (a re-run resumes).
#   make campaign-smoke   8 cells (lmpc, eso-dkmpc x dlc_smoke, dlc_low_mu x Python, C ECU)
#                         -> results/campaign_smoke/
#   make campaign         the default robustness grid (252 cells: mu x speed x mass x steering
#                         lag on the double lane change, the paper's four controllers on the
#                         Python ECU and the three the C ECU has on build/firmware/ecu; it runs
#                         make firmware first) -> results/campaign_robustness/
#   CAMPAIGN_ARGS="--address 127.0.0.1:6379 --workers 8"   an existing Ray cluster
.PHONY: campaign campaign-smoke campaign-test

CAMPAIGN_ARGS ?=
CAMPAIGN_SMOKE_OUT := results/campaign_smoke
CAMPAIGN_OUT := results/campaign_robustness
CAMPAIGN_INPUTS = $(PROVENANCE_HIL) $(PROVENANCE_DMDC)
# A grid with C ECU cells also ran the firmware (its sources and generators: mk/firmware.mk).
CAMPAIGN_C_INPUTS = $(wildcard firmware/src/*.[ch]) $(FW_TOOLS)

## 8-cell campaign on a local Ray (two controllers x two scenarios x Python, C ECU) -> results/campaign_smoke/
campaign-smoke: setup firmware
	$(PY) -m studies.campaign smoke --out $(CAMPAIGN_SMOKE_OUT) $(CAMPAIGN_ARGS)
	$(PROVENANCE_STAMP) $(addprefix $(CAMPAIGN_SMOKE_OUT)/,cells.csv summary.md heatmap_e_y_rmse.png) \
		--command "$(call provenance_command,campaign-smoke,CAMPAIGN_ARGS)" \
		--inputs $(CAMPAIGN_INPUTS) $(CAMPAIGN_C_INPUTS) studies/campaign/grids/smoke.toml \
		--modules studies.campaign.__main__

## default robustness grid on Ray, Python and C ECU (252 cells over CAN) -> results/campaign_robustness/
campaign: setup firmware
	$(PY) -m studies.campaign robustness --out $(CAMPAIGN_OUT) $(CAMPAIGN_ARGS)
	$(PROVENANCE_STAMP) $(addprefix $(CAMPAIGN_OUT)/,cells.csv summary.md heatmap_e_y_rmse.png) \
		--command "$(call provenance_command,campaign,CAMPAIGN_ARGS)" \
		--inputs $(CAMPAIGN_INPUTS) $(CAMPAIGN_C_INPUTS) studies/campaign/grids/robustness.toml \
		--modules studies.campaign.__main__

## tests of the campaign runner (with the real Ray cluster test)
campaign-test: setup
	$(PY) -m pytest -q tests/test_campaign.py
