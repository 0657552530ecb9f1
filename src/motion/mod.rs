//! Planner, interpolator and cycle loop.
pub mod cycle;
