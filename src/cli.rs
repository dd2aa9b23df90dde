//! The `qemd` command line (to be implemented).
