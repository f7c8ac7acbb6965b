//! `python/formation_swarm/layout.json`, the one source other languages read: the wire
//! payloads' layout and the protocol's constants (`formation_protocol::layout`), and every
//! observation model with its dimension and named blocks ([`Layout::blocks`]).
//!
//! A unit test keeps the file equal to the build: after a change, regenerate it with
//! `FORMATION_UPDATE_LAYOUT=1 cargo test -p formation-core layout`; the Python tests then check
//! the ctypes mirrors against it, and the Python baseline reads its offsets from it.
//! `formation-layout` prints the same JSON.

use std::fmt::Write as _;

use crate::observation::{Layout, MODELS};

/// The whole of `layout.json`.
pub fn layout_json() -> String {
    formation_protocol::layout::layout_json_with(&observation_models_json())
}

/// The `"observation_models"` member: each model's name, dimension and blocks (name, first
/// float, the names of its floats and what each measures).
fn observation_models_json() -> String {
    let quoted = |names: &[&str]| {
        let list: Vec<String> = names.iter().map(|name| format!("\"{name}\"")).collect();
        list.join(", ")
    };
    let mut out = String::from("  \"observation_models\": [");
    for (i, model) in MODELS.into_iter().enumerate() {
        let layout = Layout::of(model);
        let sep = if i == 0 { "" } else { "," };
        let _ = write!(
            out,
            "{sep}\n    {{\"name\": \"{}\", \"dim\": {}, \"blocks\": [",
            model.as_str(),
            layout.dim()
        );
        for (j, block) in layout.blocks().iter().enumerate() {
            let sep = if j == 0 { "" } else { "," };
            let kinds: Vec<&str> = block.kinds.iter().map(|kind| kind.as_str()).collect();
            let _ = write!(
                out,
                "{sep}\n      {{\"name\": \"{}\", \"offset\": {}, \"fields\": [{}], \"kinds\": [{}]}}",
                block.name,
                block.offset,
                quoted(block.fields),
                quoted(&kinds)
            );
        }
        out.push_str("\n    ]}");
    }
    out.push_str("\n  ]");
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `python/formation_swarm/layout.json` is this build's layout: the Python mirrors and the
    /// Python baseline read that file, so it must never drift from Rust.
    #[test]
    fn python_layout_file_matches_the_build() {
        let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../python/formation_swarm/layout.json");
        let expected = layout_json();
        if std::env::var_os("FORMATION_UPDATE_LAYOUT").is_some() {
            std::fs::write(&path, &expected).expect("write layout.json");
        }
        let found = std::fs::read_to_string(&path).unwrap_or_default();
        assert!(
            found == expected,
            "{} differs from this build's layout: regenerate it with \
             `FORMATION_UPDATE_LAYOUT=1 cargo test -p formation-core layout`, update \
             python/formation_swarm/wire.py and bump PROTOCOL_VERSION if a payload changed. \
             This build's layout:\n{expected}",
            path.display()
        );
    }

    #[test]
    fn every_model_is_in_the_json_with_its_dimension() {
        let json = layout_json();
        for model in MODELS {
            let entry = format!(
                "{{\"name\": \"{}\", \"dim\": {}",
                model.as_str(),
                Layout::of(model).dim()
            );
            assert!(json.contains(&entry), "{entry} in\n{json}");
        }
    }
}
