"""TTP-deviation models (paper eq. 11-13): features, regression, model types, policy and metrics."""
