//! Every struct a shader shares with the host has the host's layout.
//!
//! WGSL has no includes, so each shader declares the uniform and storage
//! structs it reads (`Params` in eight shaders, `Chunk` in three, `ColState`
//! in f32 and f64). This test parses every production shader with naga (the
//! f64 variants as `precision::f64_source` makes them) and checks each
//! declaration against its `#[repr(C)]` twin on the host: the same size, and
//! every host field at the same offset under the same name. A struct a
//! shader declares without a host twin must be listed as device-only.

use std::mem::{offset_of, size_of};
use wgpu::naga;

/// A host struct as a shader must declare it.
struct Host {
    /// The struct's name in the shader.
    name: &'static str,
    size: usize,
    /// The host's named fields and their offsets (padding arrays left out:
    /// the size covers them).
    fields: Vec<(&'static str, usize)>,
}

macro_rules! host {
    ($name:literal, $t:ty, $($f:ident),+) => {
        Host {
            name: $name,
            size: size_of::<$t>(),
            fields: vec![$((stringify!($f), offset_of!($t, $f))),+],
        }
    };
}

/// Structs that live on the device only (packed from `u32` arrays on the
/// host, or a shader's own working values), per shader.
const DEVICE_ONLY: [(&str, &str); 5] = [
    ("supernodal.wgsl", "Super"),
    ("supernodal.wgsl", "OwnRow"),
    ("supernodal_factor.wgsl", "Super"),
    ("supernodal_factor.wgsl", "TrailingItem"),
    ("refine_product.wgsl", "Block"),
];

/// A struct as a shader declares it: name, size, and (member, offset).
type Declared = (String, u32, Vec<(String, u32)>);

/// Each named struct of a module.
fn structs(name: &str, source: &str) -> Vec<Declared> {
    let module = naga::front::wgsl::parse_str(source)
        .unwrap_or_else(|e| panic!("{name}: {}", e.emit_to_string(source)));
    module
        .types
        .iter()
        .filter_map(|(_, ty)| match &ty.inner {
            naga::TypeInner::Struct { members, span } => Some((
                ty.name.clone()?,
                *span,
                members
                    .iter()
                    .map(|m| (m.name.clone().unwrap_or_default(), m.offset))
                    .collect(),
            )),
            _ => None,
        })
        .collect()
}

#[test]
fn every_shader_struct_has_its_host_twins_layout() {
    use crate::precision::f64_source;
    let params = || host!("Params", crate::device::Params, rows, ncols, n, groups, bs);
    let chunk = || {
        host!(
            "Chunk",
            crate::matrix::ChunkParams,
            row0,
            row1,
            group0,
            block0
        )
    };
    // The f32 and f64 column states: the same fields in both precisions.
    macro_rules! col_state {
        ($t:ty) => {
            host!("ColState", $t, rz, pap, alpha, beta, rr, thr, done, iters)
        };
    }
    let col32 = || col_state!(crate::pcg::ColState);
    let col64 = || col_state!(crate::pcg::ColState64);
    let cases: Vec<(&str, String, Vec<Host>)> = vec![
        (
            "pcg.wgsl",
            crate::pcg::SOURCE.into(),
            vec![params(), col32()],
        ),
        (
            "pcg.wgsl (f64)",
            f64_source(crate::pcg::SOURCE),
            vec![params(), col64()],
        ),
        (
            "block_jacobi.wgsl",
            crate::block_jacobi::SOURCE.into(),
            vec![params()],
        ),
        (
            "bsr_spmv.wgsl",
            crate::bsr_spmv::SOURCE.into(),
            vec![params(), chunk()],
        ),
        (
            "bsr_spmv_f64.wgsl",
            crate::bsr_spmv::F64_SOURCE.into(),
            vec![params(), chunk()],
        ),
        (
            "csr_spmv.wgsl",
            crate::csr_spmv::SOURCE.into(),
            vec![params()],
        ),
        (
            "csr_spmv.wgsl (f64)",
            f64_source(crate::csr_spmv::SOURCE),
            vec![params()],
        ),
        ("dot.wgsl", crate::dot::SOURCE.into(), vec![params()]),
        (
            "refine.wgsl",
            crate::refine::SOURCE.into(),
            vec![params(), col64()],
        ),
        (
            "refine_product.wgsl",
            crate::refine::PRODUCT_SOURCE.into(),
            vec![params(), chunk()],
        ),
        (
            "amg.wgsl",
            crate::amg_gpu::SOURCE.into(),
            vec![host!(
                "AmgParams",
                crate::amg_gpu::AmgParams,
                rows,
                n,
                nx,
                groups,
                mode,
                omega,
                row0,
                block0
            )],
        ),
        (
            "convert.wgsl",
            crate::convert::SOURCE.into(),
            vec![host!("ConvertParams", crate::convert::ConvertParams, n)],
        ),
        (
            "expand_blocks.wgsl",
            crate::expand_blocks::SOURCE.into(),
            vec![host!(
                "ExpandParams",
                crate::expand_blocks::ExpandParams,
                block0,
                blocks,
                split,
                pad
            )],
        ),
        (
            "sum_shape_blocks.wgsl",
            crate::expand_blocks::SUM_SOURCE.into(),
            vec![host!(
                "SumParams",
                crate::expand_blocks::SumParams,
                slots,
                square,
                block0,
                pair0,
                bits,
                pad0,
                pad1,
                pad2
            )],
        ),
        (
            "scale_rows.wgsl",
            crate::scale_rows::SOURCE.into(),
            vec![host!("ScaleParams", crate::scale_rows::ScaleParams, n, bs)],
        ),
        (
            "power_sum_newton.wgsl",
            crate::power_sum_newton::SOURCE.into(),
            vec![
                host!(
                    "NewtonParams",
                    crate::power_sum_newton::NewtonParams,
                    n,
                    ge,
                    gn
                ),
                host!(
                    "State",
                    crate::power_sum_newton::NewtonState,
                    done,
                    steps,
                    max_steps,
                    tol_res,
                    tol_moved,
                    floor,
                    max_res,
                    alpha,
                    moved,
                    values,
                    lambda
                ),
            ],
        ),
        (
            "supernodal.wgsl",
            crate::supernodal::SOURCE.into(),
            vec![host!(
                "Params",
                crate::supernodal::SnParams,
                own,
                n_own,
                below,
                n_below,
                nv,
                stride,
                bs,
                update0,
                update1,
                first
            )],
        ),
        (
            "supernodal_factor.wgsl",
            crate::factorize::SOURCE.into(),
            vec![host!(
                "FParams",
                crate::factorize::FactorParams,
                sn0,
                n_sn,
                v0,
                nval,
                n,
                nnz_k,
                slots,
                o_sn,
                o_rows,
                o_tptr,
                o_tpos,
                o_owner,
                o_slot_owner,
                o_order,
                o_map,
                o_task,
                task0,
                n_task,
                kb,
                o_xo,
                o_gvo,
                c1,
                lpr,
                o_dptr,
                o_dlist
            )],
        ),
    ];
    // Every production shader is here (stream.wgsl is the kernel
    // benchmark's read ceiling, behind `bench-kernels`).
    let dir = concat!(env!("CARGO_MANIFEST_DIR"), "/../shaders");
    for entry in std::fs::read_dir(dir).expect("shaders/ directory") {
        let file = entry.unwrap().file_name().to_string_lossy().into_owned();
        if file.ends_with(".wgsl") && file != "stream.wgsl" {
            assert!(
                cases.iter().any(|(name, _, _)| *name == file),
                "{file}: not checked against the host's structs"
            );
        }
    }
    for (name, source, hosts) in &cases {
        let declared = structs(name, source);
        for (sname, span, members) in &declared {
            let file = name.split(' ').next().unwrap();
            let twin = hosts.iter().find(|h| h.name == sname);
            let Some(h) = twin else {
                assert!(
                    DEVICE_ONLY.contains(&(file, sname.as_str())),
                    "{name}: struct {sname} has no host twin in this test"
                );
                continue;
            };
            assert_eq!(*span as usize, h.size, "{name}: size of {sname}");
            for (field, offset) in &h.fields {
                let got = members.iter().find(|(m, _)| m == field);
                assert_eq!(
                    got.map(|(_, o)| *o as usize),
                    Some(*offset),
                    "{name}: {sname}.{field}"
                );
            }
        }
        for h in hosts {
            assert!(
                declared.iter().any(|(s, _, _)| s == h.name),
                "{name}: declares no struct {}",
                h.name
            );
        }
    }
}
