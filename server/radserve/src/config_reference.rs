//! The configuration reference, generated from the config types: every key with its default, its
//! environment variable and its doc comment (read through the types' JSON schema, schemars), printed
//! by `radserve config --defaults` (a commented TOML file) and `radserve config --markdown` (the
//! table of docs/configuration.md, which a test holds to this output).

use serde_json::Value;

use crate::config::Config;

/// One key of the configuration tree.
#[derive(Clone, Debug, PartialEq)]
pub struct Key {
    pub section: String,
    pub name: String,
    /// Its value in the configuration read (the default, for `keys()`) as TOML text; None when unset.
    pub value: Option<String>,
    /// The key's doc comment, one paragraph.
    pub description: String,
}

impl Key {
    /// The environment variable that overrides it.
    pub fn env_var(&self) -> String {
        format!("RADSERVE__{}__{}", self.section.to_uppercase(), self.name.to_uppercase())
    }
}

/// A TOML literal of a JSON value (strings as JSON strings, which TOML reads the same; a table as an
/// inline table, whose `key = value` syntax is TOML's, not JSON's).
fn toml_literal(value: &Value) -> Option<String> {
    match value {
        Value::Null => None,
        Value::Array(items) => Some(format!("[{}]", items.iter().filter_map(toml_literal).collect::<Vec<_>>().join(", "))),
        Value::Object(entries) => {
            let fields: Vec<String> = entries
                .iter()
                .filter_map(|(name, entry)| toml_literal(entry).map(|literal| format!("{name} = {literal}")))
                .collect();
            Some(format!("{{ {} }}", fields.join(", ")))
        }
        Value::Bool(_) | Value::Number(_) | Value::String(_) => Some(value.to_string()),
    }
}

/// The schema an entry of `properties` describes, following a `$ref` into `$defs`.
fn resolve<'a>(schema: &'a Value, root: &'a Value) -> &'a Value {
    match schema.get("$ref").and_then(Value::as_str).and_then(|path| path.strip_prefix("#/$defs/")) {
        Some(name) => &root["$defs"][name],
        None => schema,
    }
}

/// Every key of every section with its default, sections and keys in alphabetical order.
pub fn keys() -> Vec<Key> {
    keys_of(&Config::default())
}

/// Every key with its value in `config`.
pub fn keys_of(config: &Config) -> Vec<Key> {
    let root = serde_json::to_value(schemars::schema_for!(Config)).expect("a schema serializes");
    let values = serde_json::to_value(config).expect("a configuration serializes");
    let mut keys = Vec::new();
    let sections = root["properties"].as_object().expect("the config is a table of sections");
    for (section, section_schema) in sections {
        let properties = resolve(section_schema, &root)["properties"].as_object().expect("each section is a table");
        for (name, property) in properties {
            let description = property
                .get("description")
                .or_else(|| resolve(property, &root).get("description"))
                .and_then(Value::as_str)
                .unwrap_or_default();
            keys.push(Key {
                section: section.clone(),
                name: name.clone(),
                value: toml_literal(&values[section][name]),
                description: description.split_whitespace().collect::<Vec<_>>().join(" "),
            });
        }
    }
    keys
}

/// `text` wrapped at `width` columns, each line starting with `prefix` and a space.
fn wrapped(text: &str, prefix: &str, width: usize) -> String {
    let mut lines: Vec<String> = Vec::new();
    for word in text.split_whitespace() {
        match lines.last_mut() {
            Some(line) if line.len() + 1 + word.len() <= width => {
                line.push(' ');
                line.push_str(word);
            }
            _ => lines.push(format!("{prefix} {word}")),
        }
    }
    lines.iter().map(|line| format!("{line}\n")).collect()
}

/// The whole configuration as a commented TOML file of its defaults: a starting point for
/// `serve --config`. Keys unset by default are commented out.
pub fn defaults_toml() -> String {
    toml_of(&Config::default(), "radserve's configuration with every default (`radserve config --defaults`)")
}

/// `config` as a commented TOML file, under a first comment line naming what it is.
pub fn toml_of(config: &Config, title: &str) -> String {
    let mut out = format!(
        "# {title}. Each key can also be\n\
         # set by the environment variable named under it, which wins over a file.\n"
    );
    let mut section = String::new();
    for key in keys_of(config) {
        if key.section != section {
            out.push_str(&format!("\n[{}]\n", key.section));
            section.clone_from(&key.section);
        }
        out.push_str(&wrapped(&key.description, "#", 100));
        out.push_str(&format!("# env: {}\n", key.env_var()));
        match &key.value {
            Some(value) => out.push_str(&format!("{} = {value}\n", key.name)),
            None => out.push_str(&format!("# {} = (unset)\n", key.name)),
        }
    }
    out
}

/// The reference table of docs/configuration.md.
pub fn markdown() -> String {
    let mut out = String::new();
    let mut section = String::new();
    for key in keys() {
        if key.section != section {
            if !section.is_empty() {
                out.push('\n');
            }
            out.push_str(&format!("### [{}]\n\n| key | default | environment variable | meaning |\n|---|---|---|---|\n", key.section));
            section.clone_from(&key.section);
        }
        let default = key.value.as_deref().map_or("unset".to_string(), |value| format!("`{value}`"));
        out.push_str(&format!("| `{}` | {default} | `{}` | {} |\n", key.name, key.env_var(), key.description.replace('|', "\\|")));
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_key_is_described_and_has_its_default() {
        let keys = keys();
        for key in &keys {
            assert!(!key.description.is_empty(), "{}.{} has no doc comment: document it in config.rs (or core's Limits)", key.section, key.name);
        }
        let address = keys.iter().find(|key| key.section == "server" && key.name == "address").unwrap();
        assert_eq!(address.value.as_deref(), Some("\"127.0.0.1:50051\""));
        assert_eq!(address.env_var(), "RADSERVE__SERVER__ADDRESS");
        let tokens = keys.iter().find(|key| key.section == "auth" && key.name == "tokens_file").unwrap();
        assert_eq!(tokens.value, None);
        // Every section of the tree, every field of Limits (from core) included.
        let limits = keys.iter().filter(|key| key.section == "limits").count();
        assert_eq!(limits, serde_json::to_value(radserve_core::Limits::default()).unwrap().as_object().unwrap().len());
    }

    #[test]
    fn tables_are_written_as_toml_inline_tables() {
        let value = serde_json::json!({"limits": {"max": 3, "name": "a"}, "unset": null});
        assert_eq!(toml_literal(&value).unwrap(), r#"{ limits = { max = 3, name = "a" } }"#);
    }

    #[test]
    fn the_defaults_file_loads_back_as_the_defaults() {
        let path = std::env::temp_dir().join(format!("radserve-defaults-{}.toml", std::process::id()));
        std::fs::write(&path, defaults_toml()).unwrap();
        use figment::providers::Format;
        let loaded = figment::Figment::from(figment::providers::Toml::file(&path)).extract::<Config>();
        std::fs::remove_file(&path).unwrap();
        assert_eq!(loaded.unwrap(), Config::default());
    }
}
