#![no_main]
//! `cargo fuzz run vtk_xml`: see `librplus_server::fuzz`.
libfuzzer_sys::fuzz_target!(|data: &[u8]| librplus_server::fuzz::run("vtk_xml", data));
