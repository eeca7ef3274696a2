//! Generates the message types from the repository's schema files (proto/swarm/v1), the
//! single source of truth the Python emulator's code is generated from too. Needs `protoc`
//! (Debian's protobuf-compiler) on PATH, or PROTOC naming it.
use std::path::PathBuf;

fn main() -> std::io::Result<()> {
    let root = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../proto");
    let dir = root.join("swarm/v1");
    let mut files: Vec<PathBuf> =
        std::fs::read_dir(&dir)?.filter_map(|e| e.ok().map(|e| e.path())).filter(|p| p.extension().is_some_and(|x| x == "proto")).collect();
    files.sort();
    for f in &files {
        println!("cargo:rerun-if-changed={}", f.display());
    }
    prost_build::compile_protos(&files, &[root])
}
