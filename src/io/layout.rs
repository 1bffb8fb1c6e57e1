//! layout.json.
