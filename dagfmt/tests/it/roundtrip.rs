//! Builder → bytes → reader round trips (property tests).
