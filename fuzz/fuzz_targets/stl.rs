#![no_main]
//! `cargo fuzz run stl`: see `librplus_server::fuzz`.
libfuzzer_sys::fuzz_target!(|data: &[u8]| librplus_server::fuzz::run("stl", data));
