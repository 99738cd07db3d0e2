//! Every kernel listed in `relfusion_shaders::ALL` must parse and validate with naga, with the
//! capabilities of a baseline WebGPU device: the kernels have to run on any adapter wgpu offers,
//! including Mesa lavapipe (the CPU fallback). A kernel that needs more must say so here.

use naga::valid::{Capabilities, ValidationFlags, Validator};

/// What every kernel may use: naga's default set, i.e. core WebGPU.
fn capabilities() -> Capabilities {
    Capabilities::default()
}

#[test]
fn every_kernel_parses_and_validates() {
    assert!(
        !relfusion_shaders::ALL.is_empty(),
        "no kernel listed in ALL"
    );
    let mut failures = Vec::new();
    for (name, source) in relfusion_shaders::ALL {
        let module = match naga::front::wgsl::parse_str(source) {
            Ok(module) => module,
            Err(e) => {
                failures.push(format!("{name}: parse error\n{}", e.emit_to_string(source)));
                continue;
            }
        };
        let mut validator = Validator::new(ValidationFlags::all(), capabilities());
        if let Err(e) = validator.validate(&module) {
            failures.push(format!(
                "{name}: validation error\n{}",
                e.emit_to_string(source)
            ));
            continue;
        }
        let entry = module
            .entry_points
            .iter()
            .find(|ep| ep.name == relfusion_shaders::ENTRY_POINT);
        match entry {
            Some(ep) if ep.stage == naga::ShaderStage::Compute => {}
            Some(_) => failures.push(format!("{name}: `main` is not a compute entry point")),
            None => failures.push(format!("{name}: no `main` entry point")),
        }
    }
    assert!(
        failures.is_empty(),
        "invalid kernels:\n{}",
        failures.join("\n")
    );
}

#[test]
fn kernel_names_are_unique() {
    let mut names: Vec<&str> = relfusion_shaders::ALL.iter().map(|(n, _)| *n).collect();
    names.sort_unstable();
    let before = names.len();
    names.dedup();
    assert_eq!(before, names.len(), "duplicate kernel names in ALL");
}

/// The validator must actually reject broken kernels, otherwise the test above proves nothing.
#[test]
fn validator_rejects_a_broken_kernel() {
    let broken = "@compute @workgroup_size(1) fn main() { let x: u32 = 1.5; }";
    let parsed = naga::front::wgsl::parse_str(broken);
    let rejected = match parsed {
        Err(_) => true,
        Ok(module) => Validator::new(ValidationFlags::all(), capabilities())
            .validate(&module)
            .is_err(),
    };
    assert!(rejected, "a type error was accepted");
}
