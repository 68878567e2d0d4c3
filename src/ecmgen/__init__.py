"""ecmgen: cell test data -> 2RC equivalent-circuit model -> C code for BMS firmware.

Pipeline (one module per stage):
    measure   measurement files -> TimeSeries
    dcir      pulse test -> DC-IR table
    ocv       OCV table from a table, a low-rate test or pulse-test rests
    fit_points  GA / casadi-LM fits of the paper's five-point DC-IR curves
    fit_curve   whole-pulse-curve (pulse + relaxation) fit
    model     EcmModel and the versioned model.json
    simulate  discrete 2RC simulation and validation metrics
    pipeline  the `build` chain behind the CLI
"""

__version__ = "0.1.0"
