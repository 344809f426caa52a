//! Odometry-based submaps (seed 000 §4.4, eq. 4.11).
