//! Pd-series inverter model.
