"""Measurements, configuration, geodesy, bag ingestion, the estimator interface and the smoother."""
