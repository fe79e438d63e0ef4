//! The build-time check of the GPU backend's WGSL (build.rs; also
//! tests/wgsl_build.rs, which feeds it broken copies): every module
//! src/render/gpu/wgsl.rs assembles is parsed and validated by naga, the
//! shader compiler wgpu itself uses, with its override constants left
//! overridable (each has a default in the source).

use naga::valid::{Capabilities, ValidationFlags, Validator};

use super::wgsl::Module;

/// Parses and validates one assembled module; `Err` names the .wgsl file
/// and line of the error, then gives naga's report on the module's text.
pub fn validate(m: &Module) -> Result<(), String> {
    let report = |emitted: String| {
        // naga's report points at `NAME:LINE:COLUMN` of the module's text.
        let line = emitted
            .split(&format!("{}:", m.name))
            .nth(1)
            .and_then(|rest| rest.split(':').next()?.parse::<usize>().ok());
        let at = line.map_or(String::new(), |l| {
            let offset = m.text.split_inclusive('\n').take(l - 1).map(str::len).sum();
            let (file, line) = m.locate(offset);
            format!("{file}:{line}: ")
        });
        format!("{at}invalid WGSL in module {}:\n{emitted}", m.name)
    };
    let module = naga::front::wgsl::parse_str(&m.text)
        .map_err(|e| report(e.emit_to_string_with_path(&m.text, &m.name)))?;
    Validator::new(ValidationFlags::all(), Capabilities::default())
        .validate(&module)
        .map_err(|e| report(e.emit_to_string_with_path(&m.text, &m.name)))?;
    Ok(())
}

/// Validates every module; `Err` joins the reports of all that fail.
pub fn validate_all(modules: &[Module]) -> Result<(), String> {
    let errors: Vec<String> = modules.iter().filter_map(|m| validate(m).err()).collect();
    if errors.is_empty() {
        Ok(())
    } else {
        Err(errors.join("\n"))
    }
}
