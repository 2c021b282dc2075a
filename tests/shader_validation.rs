//! Every WGSL shader in `shaders/` parses and validates with naga (the same
//! front end wgpu uses), without a GPU.

use solver_gpu::naga;

/// Shaders that also compile in f64 (solver_gpu::precision).
const F64_VARIANTS: [&str; 2] = ["pcg.wgsl", "csr_spmv.wgsl"];
/// Shaders written with f64 (they need SHADER_F64, naga's FLOAT64).
const F64_ONLY: [&str; 8] = [
    "convert.wgsl",
    "supernodal_factor.wgsl",
    "power_sum_newton.wgsl",
    "bsr_spmv_f64.wgsl",
    "expand_blocks.wgsl",
    "sum_shape_blocks.wgsl",
    "refine.wgsl",
    "refine_product.wgsl",
];

/// The f64 variant parses, validates with the FLOAT64 capability, and has no
/// f32 left.
fn validate_f64(name: &str, source: &str) {
    let f64_source = solver_gpu::precision::f64_source(source);
    assert!(!f64_source.contains("f32"), "{name} (f64) still has f32");
    let module = naga::front::wgsl::parse_str(&f64_source)
        .unwrap_or_else(|e| panic!("{name} (f64): {}", e.emit_to_string(&f64_source)));
    naga::valid::Validator::new(
        naga::valid::ValidationFlags::all(),
        naga::valid::Capabilities::FLOAT64,
    )
    .validate(&module)
    .unwrap_or_else(|e| panic!("{name} (f64): {}", e.emit_to_string(&f64_source)));
    assert!(
        !module.entry_points.is_empty(),
        "{name} (f64): no entry point"
    );
}

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
        let capabilities = if F64_ONLY.contains(&name.as_str()) {
            naga::valid::Capabilities::FLOAT64
        } else {
            naga::valid::Capabilities::empty()
        };
        let mut validator =
            naga::valid::Validator::new(naga::valid::ValidationFlags::all(), capabilities);
        validator
            .validate(&module)
            .unwrap_or_else(|e| panic!("{name}: {}", e.emit_to_string(&source)));
        assert!(!module.entry_points.is_empty(), "{name}: no entry point");
        if F64_VARIANTS.contains(&name.as_str()) {
            validate_f64(&name, &source);
        }
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
        "convert.wgsl",
        "bsr_spmv_f64.wgsl",
        "stream.wgsl",
        "expand_blocks.wgsl",
        "sum_shape_blocks.wgsl",
        "supernodal.wgsl",
        "supernodal_factor.wgsl",
        "refine.wgsl",
        "refine_product.wgsl",
        "power_sum_newton.wgsl",
    ] {
        assert!(names.iter().any(|n| n == expected), "{expected} missing");
    }
}
