//! The `lightfuse` command line.
