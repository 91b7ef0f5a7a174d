"""The fault campaign's run-and-verdict half (``make faults``, docs/faults.md): the cases
(`catalogue`), one case's run against the Python or the C ECU on the HIL rig (`runs`,
`python_ecu`, `c_ecu`, `relay`) and its verdict (`verdicts`). The campaign over every case,
its executors and its report are ``studies.fault_campaign``, ``studies.fault_runs`` and
``studies.fault_report``.
"""
