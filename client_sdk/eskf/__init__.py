"""The error-state Kalman filter of the tracker core: state, propagator, one updater, initializer, options."""
