//! Compiles `librplus/v1/*.proto` with protox (pure Rust, no protoc) and writes the encoded
//! descriptor set for server reflection beside the generated code.
use prost::Message;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    println!("cargo:rerun-if-changed=librplus");
    let fds = protox::compile(["librplus/v1/librplus.proto"], ["."])?;
    let out = std::path::PathBuf::from(std::env::var("OUT_DIR")?);
    std::fs::write(out.join("librplus_descriptor.bin"), fds.encode_to_vec())?;
    tonic_prost_build::configure()
        .build_server(true)
        .build_client(true)
        // Decode failures are the client's: INVALID_ARGUMENT (src/lib.rs, `codec`).
        .codec_path("crate::codec::Checked")
        .compile_fds(fds)?;
    Ok(())
}
