//! One test per validation rule, and corruption properties.
