//! The paper's three stages, each a plain function of files (DESIGN §4).

pub mod reconstruct;
