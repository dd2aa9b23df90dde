//! Evaluation tools (to be implemented).
