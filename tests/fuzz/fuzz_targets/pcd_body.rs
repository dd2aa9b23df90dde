//! Fuzz target `pcd_body` (see tests/fuzz/common.rs).
#![no_main]

#[path = "../common.rs"]
mod common;

libfuzzer_sys::fuzz_target!(|data: &[u8]| common::pcd_body(data));
