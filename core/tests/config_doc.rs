//! docs/CONFIG.md against the code: every key of every section of the run configuration is
//! documented there with the code's default, and nothing is documented that the code lacks.
//!
//! The doc's sections are headed ``## `[section]` ``; each key is a table row whose first cell is
//! the key and whose second is its default as a TOML value, both in backticks.

use std::collections::BTreeMap;
use std::path::PathBuf;

use formation_core::config::RunConfig;

/// (section, key) -> the documented default, as written (without backticks).
type Documented = BTreeMap<(String, String), String>;

fn config_doc() -> String {
    let path = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../docs/CONFIG.md");
    std::fs::read_to_string(&path).unwrap_or_else(|err| panic!("cannot read {}: {err}", path.display()))
}

/// The text between the first pair of backticks of a table cell.
fn in_backticks(cell: &str) -> Option<&str> {
    let cell = cell.trim();
    cell.strip_prefix('`')?.strip_suffix('`')
}

/// Every key row of every ``## `[section]` `` table of the doc.
fn documented(doc: &str) -> Documented {
    let mut rows = Documented::new();
    let mut section: Option<String> = None;
    for line in doc.lines() {
        if let Some(heading) = line.strip_prefix("## ") {
            section = in_backticks(heading)
                .and_then(|name| name.strip_prefix('['))
                .and_then(|name| name.strip_suffix(']'))
                .map(str::to_owned);
            continue;
        }
        let (Some(section), Some(row)) = (&section, line.strip_prefix('|')) else {
            continue;
        };
        let cells: Vec<&str> = row.split('|').collect();
        let (Some(key), Some(default)) = (
            cells.first().and_then(|c| in_backticks(c)),
            cells.get(1).and_then(|c| in_backticks(c)),
        ) else {
            continue;
        };
        let previous = rows.insert((section.clone(), key.to_owned()), default.to_owned());
        assert!(previous.is_none(), "docs/CONFIG.md lists [{section}] {key} twice");
    }
    rows
}

/// A documented default read as TOML.
fn parse_value(section: &str, key: &str, text: &str) -> toml::Value {
    let table: toml::Table = toml::from_str(&format!("value = {text}"))
        .unwrap_or_else(|err| panic!("docs/CONFIG.md: [{section}] {key}'s default `{text}` is not TOML: {err}"));
    table
        .get("value")
        .cloned()
        .unwrap_or_else(|| panic!("docs/CONFIG.md: [{section}] {key}: no value in `{text}`"))
}

/// Equal as config values: numbers by value (`0` documents a float 0.0), the rest exactly.
fn same(documented: &toml::Value, code: &toml::Value) -> bool {
    let number = |value: &toml::Value| match value {
        toml::Value::Integer(i) => Some(*i as f64),
        toml::Value::Float(f) => Some(*f),
        _ => None,
    };
    match (documented, code) {
        (toml::Value::Array(a), toml::Value::Array(b)) => {
            a.len() == b.len() && a.iter().zip(b).all(|(x, y)| same(x, y))
        }
        _ => match (number(documented), number(code)) {
            (Some(x), Some(y)) => x == y,
            _ => documented == code,
        },
    }
}

/// The default configuration, section by section, as the run directory's `config.toml` holds it.
fn code_defaults() -> BTreeMap<String, toml::Table> {
    let value = toml::Value::try_from(RunConfig::default()).expect("the default config serialises");
    let toml::Value::Table(sections) = value else {
        panic!("the config serialises to a table");
    };
    sections
        .into_iter()
        .map(|(name, section)| match section {
            toml::Value::Table(keys) => (name, keys),
            other => panic!("config section {name} is not a table: {other}"),
        })
        .collect()
}

#[test]
fn every_config_key_is_documented_with_its_default() {
    let documented = documented(&config_doc());
    let code = code_defaults();
    assert!(code.len() >= 6, "the config has its sections: {:?}", code.keys());
    let mut missing = Vec::new();
    let mut wrong = Vec::new();
    for (section, keys) in &code {
        for (key, value) in keys {
            match documented.get(&(section.clone(), key.clone())) {
                None => missing.push(format!("[{section}] {key} (default {value})")),
                Some(text) => {
                    let doc_value = parse_value(section, key, text);
                    if !same(&doc_value, value) {
                        wrong.push(format!(
                            "[{section}] {key}: docs say `{text}`, the code's default is {value}"
                        ));
                    }
                }
            }
        }
    }
    assert!(
        missing.is_empty() && wrong.is_empty(),
        "config keys missing from docs/CONFIG.md:\n{}\ndefaults in docs/CONFIG.md that differ from the code:\n{}",
        missing.join("\n"),
        wrong.join("\n")
    );
}

#[test]
fn docs_list_no_config_key_the_code_lacks() {
    let documented = documented(&config_doc());
    let code = code_defaults();
    let unknown: Vec<String> = documented
        .keys()
        .filter(|(section, key)| !code.get(section).is_some_and(|keys| keys.contains_key(key)))
        .map(|(section, key)| format!("[{section}] {key}"))
        .collect();
    assert!(
        unknown.is_empty(),
        "docs/CONFIG.md documents keys the config does not have:\n{}",
        unknown.join("\n")
    );
}

#[test]
fn the_documented_defaults_as_a_file_are_the_default_config() {
    // The doc's defaults written out as a config file: parsing and validating it must give
    // exactly the default configuration (so every documented default is also a valid value).
    let mut file = String::new();
    let mut section = String::new();
    for ((name, key), text) in documented(&config_doc()) {
        if name != section {
            file.push_str(&format!("\n[{name}]\n"));
            section = name;
        }
        file.push_str(&format!("{key} = {text}\n"));
    }
    let parsed = RunConfig::from_toml_str(&file).unwrap_or_else(|err| panic!("{err}\n{file}"));
    assert_eq!(parsed, RunConfig::default(), "the documented defaults:\n{file}");
}

#[test]
fn the_reader_finds_rows_and_ignores_other_tables() {
    let doc = "# T\n\n## `[env]`\n\n| key | default | range | meaning |\n|---|---|---|---|\n\
               | `dt_s` | `0.1` | (0, 1] | step |\n\n## Not in the file\n\n| `x` | `1` | | |\n";
    let rows = documented(doc);
    assert_eq!(rows.len(), 1, "{rows:?}");
    assert_eq!(
        rows.get(&("env".into(), "dt_s".into())).map(String::as_str),
        Some("0.1")
    );
    assert!(same(&parse_value("env", "dt_s", "0"), &toml::Value::Float(0.0)));
    assert!(!same(&parse_value("env", "dt_s", "0.2"), &toml::Value::Float(0.1)));
}
