//! Every WGSL shader in `shaders/` parses and validates with naga (the same
//! front end wgpu uses), without a GPU.

use solver_gpu::naga;

#[test]
fn every_shader_parses_and_validates() {
    let dir = concat!(env!("CARGO_MANIFEST_DIR"), "/shaders");
    let mut names = Vec::new();
    for entry in std::fs::read_dir(dir).expect("shaders/ directory") {
        let path = entry.unwrap().path();
        if path.extension().and_then(|e| e.to_str()) != Some("wgsl") {
            continue;
        }
        let source = std::fs::read_to_string(&path).unwrap();
        let name = path.file_name().unwrap().to_string_lossy().into_owned();
        let module = naga::front::wgsl::parse_str(&source)
            .unwrap_or_else(|e| panic!("{name}: {}", e.emit_to_string(&source)));
        let mut validator = naga::valid::Validator::new(
            naga::valid::ValidationFlags::all(),
            naga::valid::Capabilities::empty(),
        );
        validator
            .validate(&module)
            .unwrap_or_else(|e| panic!("{name}: {}", e.emit_to_string(&source)));
        assert!(!module.entry_points.is_empty(), "{name}: no entry point");
        names.push(name);
    }
    names.sort();
    eprintln!("validated: {names:?}");
    assert!(!names.is_empty(), "no .wgsl file found in {dir}");
    for expected in [
        "bsr_spmv.wgsl",
        "csr_spmv.wgsl",
        "dot.wgsl",
        "block_jacobi.wgsl",
        "pcg.wgsl",
    ] {
        assert!(names.iter().any(|n| n == expected), "{expected} missing");
    }
}
