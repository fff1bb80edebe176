#![no_main]
//! `cargo fuzz run physics_json`: see `librplus_server::fuzz`.
libfuzzer_sys::fuzz_target!(|data: &[u8]| librplus_server::fuzz::run("physics_json", data));
