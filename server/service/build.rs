use std::path::PathBuf;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    // A protoc shipped inside a crate, so that building needs nothing installed by hand.
    std::env::set_var("PROTOC", protoc_bin_vendored::protoc_bin_path()?);
    let proto_root = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../proto");
    let radserve = proto_root.join("radserve/v1/radserve.proto");
    // DeepMind's dm_env_rpc, served beside radserve's own API on the same port.
    let dm_env_rpc = proto_root.join("dm_env_rpc/v1/dm_env_rpc.proto");
    let status = proto_root.join("google/rpc/status.proto");
    let descriptor = PathBuf::from(std::env::var("OUT_DIR")?).join("radserve_descriptor.bin");
    tonic_prost_build::configure()
        .file_descriptor_set_path(&descriptor)
        .bytes(".radserve.v1.Tensor.data")
        .bytes(".radserve.v1.BatchChunk.data")
        .codec_path("crate::codec::StrictCodec")
        .compile_protos(&[&radserve, &dm_env_rpc], &[&proto_root])?;
    for file in [&radserve, &dm_env_rpc, &status] {
        println!("cargo:rerun-if-changed={}", file.display());
    }
    Ok(())
}
