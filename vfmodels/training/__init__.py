"""Training the force models: `regressor` (ForceRegressor, the LightningModule around any network),
`train` (the LightningCLI behind train.py) with its callbacks (`checkpoint`, `early_stopping`,
`epoch_timer`, `progress`, `prediction_writer`), its configs (`config_files`), its messages
(`cli_errors`, `quiet`) and its run folder (`run_folder`)."""
