//! Environment ids (`family/name`), the options each family accepts, and their defaults.
//!
//! Options are resolved here, in Rust, before any worker is asked for anything: an unknown option, a
//! value of the wrong type or out of range is answered at once with what was expected.

use std::collections::BTreeMap;
use std::fmt;

use serde::{Deserialize, Serialize};

use crate::error::CoreError;

#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize)]
pub enum Family {
    /// DeepMind Control Suite, rendered to pixels by default.
    Dmc,
    /// gymnasium MuJoCo and classic-control tasks, state observations.
    Gym,
    /// ProcGen games through its gym3 API, 64x64 RGB.
    Procgen,
}

impl Family {
    pub const ALL: [Family; 3] = [Family::Dmc, Family::Gym, Family::Procgen];

    pub fn prefix(self) -> &'static str {
        match self {
            Family::Dmc => "dmc",
            Family::Gym => "gym",
            Family::Procgen => "procgen",
        }
    }
}

impl fmt::Display for Family {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.prefix())
    }
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub enum OptionValue {
    Bool(bool),
    Int(i64),
    Float(f64),
    Str(String),
}

impl OptionValue {
    fn kind(&self) -> &'static str {
        match self {
            OptionValue::Bool(_) => "bool",
            OptionValue::Int(_) => "int",
            OptionValue::Float(_) => "float",
            OptionValue::Str(_) => "string",
        }
    }

    pub fn as_int(&self) -> Option<i64> {
        match self {
            OptionValue::Int(value) => Some(*value),
            OptionValue::Bool(_) | OptionValue::Float(_) | OptionValue::Str(_) => None,
        }
    }

    pub fn as_bool(&self) -> Option<bool> {
        match self {
            OptionValue::Bool(value) => Some(*value),
            OptionValue::Int(_) | OptionValue::Float(_) | OptionValue::Str(_) => None,
        }
    }
}

impl fmt::Display for OptionValue {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            OptionValue::Bool(value) => write!(f, "{value}"),
            OptionValue::Int(value) => write!(f, "{value}"),
            OptionValue::Float(value) => write!(f, "{value}"),
            OptionValue::Str(value) => write!(f, "'{value}'"),
        }
    }
}

pub type Options = BTreeMap<String, OptionValue>;

/// The option the server itself consumes (frames are stacked in the server, not in workers).
pub const FRAME_STACK: &str = "frame_stack";
const MAX_FRAME_STACK: i64 = 16;
const MAX_IMAGE_SIDE: i64 = 1024;

/// What a value must satisfy, beyond having the default's type.
#[derive(Clone, Copy)]
enum Rule {
    Any,
    IntRange(i64, i64),
    OneOf(&'static [&'static str]),
}

struct OptionSchema {
    name: &'static str,
    default: OptionValue,
    rule: Rule,
}

fn option(name: &'static str, default: OptionValue, rule: Rule) -> OptionSchema {
    OptionSchema { name, default, rule }
}

/// A parsed, known environment id.
#[derive(Clone, Debug, PartialEq, Eq, Hash)]
pub struct EnvId {
    pub family: Family,
    pub name: String,
}

impl EnvId {
    pub fn full(&self) -> String {
        format!("{}/{}", self.family, self.name)
    }
}

/// Action repeat of the RAD paper's DMControl table: 2 for finger-spin and walker-walk, 8 for
/// cartpole, 4 otherwise (rad-paper.tex, appendix hyperparameters).
pub fn paper_action_repeat(dmc_name: &str) -> i64 {
    if dmc_name == "finger-spin" || dmc_name == "walker-walk" {
        2
    } else if dmc_name.starts_with("cartpole-") {
        8
    } else {
        4
    }
}

const RENDER_PROFILES: &[&str] = &["default", "fast"];
/// The option naming what steps a session's envs.
pub const ENGINE: &str = "engine";
/// A session option: the envs a `recv` returns, below `num_envs` for EnvPool's asynchronous mode.
pub const BATCH_SIZE: &str = "batch_size";
/// A session option: whether the envs' info dicts travel (true by default).
pub const SEND_INFOS: &str = "send_infos";

/// `batch_size` when `options` put a session of `num_envs` envs in EnvPool's asynchronous mode (a batch
/// below `num_envs`); None for a synchronous one.
pub fn async_batch(options: &Options, num_envs: usize) -> Option<usize> {
    match options.get(BATCH_SIZE) {
        Some(&OptionValue::Int(batch)) if batch > 0 && (batch as usize) < num_envs => Some(batch as usize),
        _ => None,
    }
}
/// Whether `options` have EnvPool's ports step the session (engine "envpool"), not the simulators' own
/// packages.
pub fn engine_is_envpool(options: &Options) -> bool {
    options.get(ENGINE) == Some(&OptionValue::Str("envpool".into()))
}

/// `batch_size` when `options` put a session of `num_envs` envs in the native engine's asynchronous
/// mode (groups of batch_size envs, each stepped whole); None otherwise.
pub fn native_async_batch(options: &Options, num_envs: usize) -> Option<usize> {
    async_batch(options, num_envs).filter(|_| !engine_is_envpool(options))
}

/// The groups the native engine's asynchronous mode steps a session in: consecutive runs of
/// `batch_size` envs (the last shorter only when num_envs is not a multiple, which create refuses).
pub fn native_async_groups(options: &Options, num_envs: usize) -> Option<Vec<std::ops::Range<usize>>> {
    native_async_batch(options, num_envs)
        .map(|batch| (0..num_envs).step_by(batch).map(|start| start..(start + batch).min(num_envs)).collect())
}

/// The most groups a session in the native engine's asynchronous mode is split into (num_envs /
/// batch_size): each is a group of its own in a worker, with its own frame memory.
pub const MAX_ASYNC_GROUPS: usize = 32;

/// "native": the simulators' own Python packages (dm_control, gymnasium, procgen), results equal to
/// theirs; "envpool": EnvPool's C++ ports of the same tasks (dm_control state tasks, MuJoCo-gym and
/// classic control, ProcGen), faster per step, results EnvPool's (radserve_worker/envpool_engine.py, EnvpoolGroup).
const ENGINES: &[&str] = &["native", "envpool"];
const DISTRIBUTION_MODES: &[&str] = &["easy", "hard", "extreme", "memory", "exploration"];

fn schema(env: &EnvId, pixels: bool) -> Vec<OptionSchema> {
    use OptionValue::{Bool, Int, Str};
    let mut options = match env.family {
        Family::Dmc => {
            let camera = if env.name.starts_with("quadruped-") { 2 } else { 0 };
            vec![
                option("pixels", Bool(true), Rule::Any),
                option("height", Int(100), Rule::IntRange(1, MAX_IMAGE_SIDE)),
                option("width", Int(100), Rule::IntRange(1, MAX_IMAGE_SIDE)),
                option("camera_id", Int(camera), Rule::IntRange(-1, 64)),
                option("action_repeat", Int(paper_action_repeat(&env.name)), Rule::IntRange(1, 1000)),
                option("render_profile", Str("default".into()), Rule::OneOf(RENDER_PROFILES)),
                option(FRAME_STACK, Int(if pixels { 3 } else { 1 }), Rule::IntRange(1, MAX_FRAME_STACK)),
            ]
        }
        Family::Gym => vec![
            option("action_repeat", Int(1), Rule::IntRange(1, 1000)),
            // 0 keeps the time limit gymnasium registers for the task.
            option("max_episode_steps", Int(0), Rule::IntRange(0, 1 << 40)),
            option(FRAME_STACK, Int(1), Rule::IntRange(1, MAX_FRAME_STACK)),
        ],
        Family::Procgen => vec![
            option("num_levels", Int(0), Rule::IntRange(0, i32::MAX as i64)),
            option("start_level", Int(0), Rule::IntRange(0, i32::MAX as i64)),
            option("distribution_mode", Str("easy".into()), Rule::OneOf(DISTRIBUTION_MODES)),
            option("restrict_themes", Bool(false), Rule::Any),
            option("use_backgrounds", Bool(true), Rule::Any),
            option("use_monochrome_assets", Bool(false), Rule::Any),
            option("center_agent", Bool(true), Rule::Any),
            option("use_sequential_levels", Bool(false), Rule::Any),
            option("paint_vel_info", Bool(false), Rule::Any),
            option("use_generated_assets", Bool(false), Rule::Any),
            // procgen's own stepping threads for a worker's vector of games; 0 (radserve's default, not
            // procgen's 4) steps them on the worker's thread (radserve_worker/procgen_games.py).
            option("num_threads", Int(0), Rule::IntRange(0, 64)),
            option(FRAME_STACK, Int(1), Rule::IntRange(1, MAX_FRAME_STACK)),
        ],
    };
    options.push(option(ENGINE, Str("native".into()), Rule::OneOf(ENGINES)));
    // EnvPool's `batch_size`: 0 (or num_envs) steps every env together; below num_envs the session is
    // stepped by send/recv, `batch_size` envs per recv (engine "envpool": EnvPool's own asynchronous
    // mode; engine "native": groups of batch_size envs stepped whole; checked against num_envs at create).
    options.push(option(BATCH_SIZE, Int(0), Rule::IntRange(0, i32::MAX as i64)));
    // false: the envs' info dicts are neither collected in the workers nor sent (StepResponse's
    // step_infos and reset_infos stay empty), for learners that never read them.
    options.push(option(SEND_INFOS, Bool(true), Rule::Any));
    options
}

/// The default options of an id: what `resolve_options` gives with no overrides.
pub fn default_options(env: &EnvId) -> Options {
    resolve_options(env, &Options::new()).expect("defaults satisfy their own schema")
}

/// Applies `overrides` to the defaults of `env`, rejecting unknown names, wrong types and values
/// out of range with a message that says what was expected.
pub fn resolve_options(env: &EnvId, overrides: &Options) -> Result<Options, CoreError> {
    use crate::bounds::{check_count, check_len, clip, MAX_OPTIONS, MAX_OPTION_NAME_BYTES, MAX_OPTION_TEXT_BYTES};
    check_count("options", overrides.len(), MAX_OPTIONS)?;
    for (name, value) in overrides {
        check_len("an option name", name, MAX_OPTION_NAME_BYTES)?;
        if let OptionValue::Str(text) = value {
            check_len(&format!("option '{}'", clip(name)), text, MAX_OPTION_TEXT_BYTES)?;
        }
    }
    let pixels = match overrides.get("pixels") {
        Some(OptionValue::Bool(value)) => *value,
        _ => true,
    };
    let schema = schema(env, pixels);
    for name in overrides.keys() {
        if !schema.iter().any(|entry| entry.name == name) {
            let accepted: Vec<&str> = schema.iter().map(|entry| entry.name).collect();
            return Err(CoreError::InvalidOption(format!(
                "unknown option '{name}' for {}; accepted options: {}",
                env.full(),
                accepted.join(", ")
            )));
        }
    }
    let mut resolved = Options::new();
    for entry in &schema {
        let value = match overrides.get(entry.name) {
            None => entry.default.clone(),
            Some(given) => check_value(env, entry, given)?,
        };
        resolved.insert(entry.name.to_string(), value);
    }
    if env.family == Family::Dmc
        && resolved[ENGINE] == OptionValue::Str("envpool".into())
        && resolved["pixels"] == OptionValue::Bool(true)
    {
        return Err(CoreError::InvalidOption(format!(
            "option 'engine' of {} is 'envpool', which hosts dm_control's state observations only: give \
             pixels=false, or engine 'native' for pixels (radserve renders them itself)",
            env.full()
        )));
    }
    Ok(resolved)
}

fn check_value(env: &EnvId, entry: &OptionSchema, given: &OptionValue) -> Result<OptionValue, CoreError> {
    let invalid = |expected: String| {
        CoreError::InvalidOption(format!(
            "option '{}' of {} must be {expected}, got {} ({})",
            entry.name,
            env.full(),
            given,
            given.kind()
        ))
    };
    let value = match (&entry.default, given) {
        (OptionValue::Float(_), OptionValue::Int(int)) => OptionValue::Float(*int as f64),
        (default, given) if default.kind() == given.kind() => given.clone(),
        (default, _) => return Err(invalid(format!("a {}", default.kind()))),
    };
    match (entry.rule, &value) {
        (Rule::IntRange(low, high), OptionValue::Int(int)) if *int < low || *int > high => {
            Err(invalid(format!("an int in [{low}, {high}]")))
        }
        (Rule::OneOf(allowed), OptionValue::Str(text)) if !allowed.contains(&text.as_str()) => {
            Err(invalid(format!("one of {}", allowed.join(", "))))
        }
        _ => Ok(value),
    }
}

/// The names every family hosts, as reported by a worker (dm_control's own task list, for one).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct EnvNames {
    pub by_family: BTreeMap<Family, Vec<String>>,
}

impl EnvNames {
    pub fn all_ids(&self) -> Vec<EnvId> {
        self.by_family
            .iter()
            .flat_map(|(family, names)| names.iter().map(|name| EnvId { family: *family, name: name.clone() }))
            .collect()
    }

    /// Parses `family/name`, answering an unknown id with the closest known ones.
    pub fn parse(&self, id: &str) -> Result<EnvId, CoreError> {
        let known = id.split_once('/').and_then(|(prefix, name)| {
            let family = Family::ALL.into_iter().find(|family| family.prefix() == prefix)?;
            let names = self.by_family.get(&family)?;
            names.iter().any(|known| known == name).then(|| EnvId { family, name: name.to_string() })
        });
        // Suggestions cost an edit distance per known id: only for ids of a plausible length.
        let suggestions = if id.len() <= crate::bounds::MAX_ID_BYTES {
            closest(id, self.all_ids().iter().map(EnvId::full))
        } else {
            Vec::new()
        };
        known.ok_or_else(|| CoreError::UnknownEnv { id: id.to_string(), suggestions })
    }
}

/// Up to three known ids close to `wanted`: same ignoring case, containing it, or a small edit away.
fn closest(wanted: &str, known: impl Iterator<Item = String>) -> Vec<String> {
    let wanted_lower = wanted.to_lowercase();
    let mut scored: Vec<(usize, String)> = known
        .filter_map(|candidate| {
            let candidate_lower = candidate.to_lowercase();
            let tail = candidate_lower.split_once('/').map_or("", |(_, name)| name).to_string();
            let distance = if candidate_lower == wanted_lower {
                0
            } else if !wanted_lower.is_empty()
                && (candidate_lower.contains(&wanted_lower) || (!tail.is_empty() && wanted_lower.contains(&tail)))
            {
                1
            } else {
                strsim::levenshtein(&wanted_lower, &candidate_lower)
            };
            let limit = 3.max(wanted.len() / 3);
            (distance <= limit).then_some((distance, candidate))
        })
        .collect();
    scored.sort();
    scored.into_iter().take(3).map(|(_, id)| id).collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn names() -> EnvNames {
        let mut by_family = BTreeMap::new();
        by_family.insert(Family::Dmc, vec!["cheetah-run".into(), "cartpole-swingup".into(), "walker-walk".into()]);
        by_family.insert(Family::Gym, vec!["HalfCheetah-v5".into()]);
        by_family.insert(Family::Procgen, vec!["bigfish".into()]);
        EnvNames { by_family }
    }

    #[test]
    fn parses_known_ids_and_suggests_close_ones() {
        let names = names();
        assert_eq!(names.parse("dmc/cheetah-run").unwrap().name, "cheetah-run");
        match names.parse("dmc/cheetah-runn") {
            Err(CoreError::UnknownEnv { suggestions, .. }) => assert_eq!(suggestions[0], "dmc/cheetah-run"),
            other => panic!("expected UnknownEnv, got {other:?}"),
        }
        match names.parse("gym/halfcheetah-v5") {
            Err(CoreError::UnknownEnv { suggestions, .. }) => assert_eq!(suggestions, vec!["gym/HalfCheetah-v5"]),
            other => panic!("expected UnknownEnv, got {other:?}"),
        }
        assert!(names.parse("atari/pong").is_err());
        assert!(names.parse("nonsense").is_err());
    }

    #[test]
    fn dmc_defaults_follow_the_paper() {
        let walker = EnvId { family: Family::Dmc, name: "walker-walk".into() };
        let defaults = default_options(&walker);
        assert_eq!(defaults["action_repeat"], OptionValue::Int(2));
        assert_eq!(defaults[FRAME_STACK], OptionValue::Int(3));
        assert_eq!(defaults["height"], OptionValue::Int(100));
        let cartpole = EnvId { family: Family::Dmc, name: "cartpole-swingup".into() };
        assert_eq!(default_options(&cartpole)["action_repeat"], OptionValue::Int(8));
        let quadruped = EnvId { family: Family::Dmc, name: "quadruped-walk".into() };
        assert_eq!(default_options(&quadruped)["camera_id"], OptionValue::Int(2));
    }

    #[test]
    fn state_mode_stacks_one_frame_unless_asked() {
        let cheetah = EnvId { family: Family::Dmc, name: "cheetah-run".into() };
        let state = resolve_options(&cheetah, &Options::from([("pixels".into(), OptionValue::Bool(false))])).unwrap();
        assert_eq!(state[FRAME_STACK], OptionValue::Int(1));
    }

    #[test]
    fn the_envpool_engine_is_for_state_observations() {
        let cheetah = EnvId { family: Family::Dmc, name: "cheetah-run".into() };
        assert_eq!(default_options(&cheetah)[ENGINE], OptionValue::Str("native".into()));
        let envpool = |pixels: bool| {
            resolve_options(&cheetah, &Options::from([
                (ENGINE.into(), OptionValue::Str("envpool".into())),
                ("pixels".into(), OptionValue::Bool(pixels)),
            ]))
        };
        assert!(envpool(false).is_ok());
        let refused = envpool(true).unwrap_err().to_string();
        assert!(refused.contains("pixels=false"), "{refused}");
        let unknown = resolve_options(&cheetah, &Options::from([(ENGINE.into(), OptionValue::Str("mjx".into()))]));
        assert!(unknown.unwrap_err().to_string().contains("one of native, envpool"));
        // Both engines have an asynchronous mode (the native engine's is checked against num_envs at create).
        let batched = |engine: &str| {
            resolve_options(&cheetah, &Options::from([
                (ENGINE.into(), OptionValue::Str(engine.into())),
                ("pixels".into(), OptionValue::Bool(false)),
                (BATCH_SIZE.into(), OptionValue::Int(8)),
            ]))
        };
        assert_eq!(batched("envpool").unwrap()[BATCH_SIZE], OptionValue::Int(8));
        assert_eq!(batched("native").unwrap()[BATCH_SIZE], OptionValue::Int(8));
        assert_eq!(default_options(&cheetah)[BATCH_SIZE], OptionValue::Int(0));
    }

    #[test]
    fn bad_options_say_what_was_expected() {
        let cheetah = EnvId { family: Family::Dmc, name: "cheetah-run".into() };
        let unknown = resolve_options(&cheetah, &Options::from([("colour".into(), OptionValue::Bool(true))]));
        assert!(unknown.unwrap_err().to_string().contains("accepted options: pixels"));
        let wrong_type = resolve_options(&cheetah, &Options::from([("height".into(), OptionValue::Str("big".into()))]));
        assert!(wrong_type.unwrap_err().to_string().contains("must be a int"));
        let out_of_range = resolve_options(&cheetah, &Options::from([(FRAME_STACK.into(), OptionValue::Int(0))]));
        assert!(out_of_range.unwrap_err().to_string().contains("[1, 16]"));
        let bigfish = EnvId { family: Family::Procgen, name: "bigfish".into() };
        let mode = resolve_options(&bigfish, &Options::from([("distribution_mode".into(), OptionValue::Str("medium".into()))]));
        assert!(mode.unwrap_err().to_string().contains("one of easy, hard"));
    }

    #[test]
    fn procgen_steps_on_the_worker_thread_unless_asked() {
        let bigfish = EnvId { family: Family::Procgen, name: "bigfish".into() };
        assert_eq!(default_options(&bigfish)["num_threads"], OptionValue::Int(0));
        let pooled = resolve_options(&bigfish, &Options::from([("num_threads".into(), OptionValue::Int(4))])).unwrap();
        assert_eq!(pooled["num_threads"], OptionValue::Int(4));
        let too_many = resolve_options(&bigfish, &Options::from([("num_threads".into(), OptionValue::Int(65))]));
        assert!(too_many.unwrap_err().to_string().contains("[0, 64]"));
    }
}
