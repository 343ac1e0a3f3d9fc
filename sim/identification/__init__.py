"""Identification in simulation: excitation data, Fisher information, classical estimators."""
