//! Planner, interpolator and cycle loop.
