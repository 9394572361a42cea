"""How good and how sure a force estimate is: `metrics` (RMSE, NRMSE, R^2) and `band` (a calibrated
band per frame and component)."""
