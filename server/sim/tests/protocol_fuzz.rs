//! Fuzzing of the worker protocol's decoder (both directions: the worker decodes requests, the
//! server decodes what a possibly broken worker sends back). Any bytes decode to an error or to a
//! message whose encoding round-trips; framed streams of any bytes never panic and never
//! allocate past the message limit. Bounded in `cargo test` (PROPTEST_CASES, default 2048);
//! `make fuzz` runs more.

use std::collections::BTreeMap;

use proptest::prelude::*;
use radserve_core::{DType, EnvNames, Family, InfoColumn, InfoKind, Infos, OptionValue, Space};
use radserve_sim::protocol::{self, EnvSpec, GroupConfig, Request, Response, StepResult, MAX_MESSAGE_BYTES};

fn config() -> ProptestConfig {
    let cases = std::env::var("PROPTEST_CASES").ok().and_then(|value| value.parse().ok()).unwrap_or(2048);
    ProptestConfig { cases, ..ProptestConfig::default() }
}

fn family() -> impl Strategy<Value = Family> {
    prop::sample::select(vec![Family::Dmc, Family::Gym, Family::Procgen])
}

fn option_value() -> impl Strategy<Value = OptionValue> {
    prop_oneof![
        any::<bool>().prop_map(OptionValue::Bool),
        any::<i64>().prop_map(OptionValue::Int),
        any::<f64>().prop_map(OptionValue::Float),
        "\\PC{0,12}".prop_map(OptionValue::Str),
    ]
}

fn options() -> impl Strategy<Value = BTreeMap<String, OptionValue>> {
    prop::collection::btree_map("[a-z_]{1,10}", option_value(), 0..4)
}

fn dtype() -> impl Strategy<Value = DType> {
    prop::sample::select(vec![DType::Uint8, DType::Int32, DType::Int64, DType::Float32, DType::Float64, DType::Bool])
}

fn space() -> impl Strategy<Value = Space> {
    let dtype = dtype();
    prop_oneof![
        (dtype, prop::collection::vec(0usize..300, 0..4), prop::collection::vec(any::<f64>(), 0..4), prop::collection::vec(any::<f64>(), 0..4))
            .prop_map(|(dtype, shape, low, high)| Space::Box { dtype, shape, low, high }),
        any::<i64>().prop_map(|n| Space::Discrete { n }),
    ]
}

fn request() -> impl Strategy<Value = Request> {
    prop_oneof![
        Just(Request::ListNames),
        prop::collection::vec((family(), "\\PC{0,16}", options()), 0..3).prop_map(|entries| Request::Specs { entries }),
        (any::<u64>(), family(), "\\PC{0,16}", options(), prop::collection::vec(any::<u64>(), 0..6))
            .prop_map(|(group, family, name, options, seeds)| Request::CreateGroup(GroupConfig { group, family, name, options, seeds })),
        (any::<u64>(), any::<usize>()).prop_map(|(group, shm_len)| Request::Attach { group, shm_len, memory: Default::default() }),
        (any::<u64>(), prop::option::of(prop::collection::vec(any::<u64>(), 0..6)), prop::option::of(prop::collection::vec(any::<bool>(), 0..6)))
            .prop_map(|(group, seeds, mask)| Request::Reset { group, seeds, mask }),
        (any::<u64>(), prop::collection::vec(any::<u8>(), 0..64), prop::option::of(prop::collection::vec(any::<bool>(), 0..6)))
            .prop_map(|(group, actions, skip)| Request::Step { group, actions, skip }),
        (any::<u64>(), prop::option::of(prop::collection::vec(any::<u64>(), 0..6)))
            .prop_map(|(group, seeds)| Request::AsyncReset { group, seeds }),
        (any::<u64>(), prop::collection::vec(any::<u8>(), 0..64), prop::collection::vec(any::<bool>(), 0..6))
            .prop_map(|(group, actions, sent)| Request::Send { group, actions, sent }),
        any::<u64>().prop_map(|group| Request::Recv { group }),
        (any::<u64>(), prop::collection::vec(any::<u8>(), 0..64), prop::collection::vec(any::<bool>(), 0..6))
            .prop_map(|(group, actions, sent)| Request::SendRecv { group, actions, sent }),
        any::<u64>().prop_map(|group| Request::CloseGroup { group }),
    ]
}

fn spec() -> impl Strategy<Value = EnvSpec> {
    (space(), space()).prop_map(|(observation, action)| EnvSpec { observation, action })
}

/// Info columns as a worker might send them: mostly consistent (envs ascending, values sized for
/// them), sometimes not (the server must refuse those, never index past them).
fn infos() -> impl Strategy<Value = Infos> {
    let kind = prop::sample::select(vec![InfoKind::Python, InfoKind::Scalar, InfoKind::Array, InfoKind::Text, InfoKind::Json]);
    let column = (
        prop::collection::vec("\\PC{0,6}", 0..3),
        kind,
        prop::collection::btree_set(0u32..8, 0..5),
        dtype(),
        prop::collection::vec(0u32..4, 0..3),
        prop::collection::vec(any::<u8>(), 0..48),
        prop::collection::vec("\\PC{0,6}", 0..5),
        any::<bool>(),
    )
        .prop_map(|(path, kind, envs, dtype, shape, bytes, texts, consistent)| {
            let envs: Vec<u32> = envs.into_iter().collect();
            if !consistent {
                return InfoColumn { path, kind, envs, dtype, shape, data: bytes, texts };
            }
            let shape = if kind == InfoKind::Array { shape } else { Vec::new() };
            let dtype = if kind == InfoKind::Python { DType::Float64 } else { dtype };
            let row = shape.iter().map(|&d| d as usize).product::<usize>() * dtype.size_of();
            let (data, texts) = match kind.numeric() {
                true => ((0..envs.len() * row).map(|i| bytes.get(i).copied().unwrap_or(0)).collect(), Vec::new()),
                false => (Vec::new(), envs.iter().map(|env| format!("{env}")).collect()),
            };
            InfoColumn { path: if path.is_empty() { vec!["k".into()] } else { path }, kind, envs, dtype, shape, data, texts }
        });
    prop::collection::vec(column, 0..3).prop_map(|columns| Infos { columns })
}

fn step_result() -> impl Strategy<Value = StepResult> {
    (0usize..6)
        .prop_flat_map(|n| (
            prop::collection::vec(any::<f64>(), n),
            prop::collection::vec(any::<bool>(), n),
            prop::collection::vec(any::<bool>(), n),
            prop::collection::vec((any::<u32>(), "\\PC{0,12}"), 0..2),
            infos(),
            infos(),
        ))
        .prop_map(|(rewards, terminated, truncated, errors, step_infos, reset_infos)| StepResult {
            rewards,
            terminated,
            truncated,
            errors,
            step_infos,
            reset_infos,
        })
}

fn response() -> impl Strategy<Value = Response> {
    prop_oneof![
        prop::collection::btree_map(family(), prop::collection::vec("\\PC{0,12}", 0..4), 0..3)
            .prop_map(|by_family| Response::Names(EnvNames { by_family })),
        prop::collection::vec(prop_oneof![spec().prop_map(Ok), "\\PC{0,12}".prop_map(Err)], 0..3).prop_map(Response::Specs),
        spec().prop_map(Response::Created),
        Just(Response::Attached),
        infos().prop_map(Response::Reset),
        step_result().prop_map(Response::Stepped),
        Just(Response::Sent),
        (prop::collection::vec(any::<bool>(), 0..6), step_result()).prop_map(|(ready, result)| Response::Received { ready, result }),
        Just(Response::Closed),
        "\\PC{0,24}".prop_map(Response::Failed),
    ]
}

/// Decoding never panics, and what decodes is a message the other side reads back as the same
/// message (its encoding decodes and re-encodes to itself).
fn check_decoder<T: serde::Serialize + serde::de::DeserializeOwned>(body: &[u8]) -> Result<(), TestCaseError> {
    if let Ok(message) = protocol::decode::<T>(body) {
        let framed = protocol::encode(&message).unwrap();
        let again: T = protocol::decode(&framed[4..]).unwrap();
        prop_assert_eq!(protocol::encode(&again).unwrap(), framed);
    }
    Ok(())
}

/// Mutations of a valid encoding: flip, overwrite, truncate or extend it at a position.
fn mutate(mut bytes: Vec<u8>, edits: &[(usize, u8, u8)]) -> Vec<u8> {
    for &(at, kind, value) in edits {
        if bytes.is_empty() {
            bytes.push(value);
            continue;
        }
        let at = at % bytes.len();
        match kind % 4 {
            0 => bytes[at] ^= value | 1,
            1 => bytes[at] = value,
            2 => bytes.truncate(at),
            _ => bytes.insert(at, value),
        }
    }
    bytes
}

fn edits() -> impl Strategy<Value = Vec<(usize, u8, u8)>> {
    prop::collection::vec((any::<usize>(), any::<u8>(), any::<u8>()), 1..4)
}

/// A valid message decodes back to its own encoding, and mutations of that encoding decode safely.
fn check_round_trip_and_mutations<T: serde::Serialize + serde::de::DeserializeOwned>(
    message: &T,
    edits: &[(usize, u8, u8)],
) -> Result<(), TestCaseError> {
    let framed = protocol::encode(message).unwrap();
    let decoded: T = protocol::decode(&framed[4..]).unwrap();
    prop_assert_eq!(protocol::encode(&decoded).unwrap(), framed.clone());
    check_decoder::<T>(&mutate(framed[4..].to_vec(), edits))
}

proptest! {
    #![proptest_config(config())]

    #[test]
    fn any_bytes_decode_to_an_error_or_a_faithful_message(body in prop::collection::vec(any::<u8>(), 0..256)) {
        check_decoder::<Request>(&body)?;
        check_decoder::<Response>(&body)?;
    }

    #[test]
    fn valid_requests_round_trip_and_their_mutations_never_panic(message in request(), edits in edits()) {
        check_round_trip_and_mutations(&message, &edits)?;
    }

    #[test]
    fn valid_responses_round_trip_and_their_mutations_never_panic(message in response(), edits in edits()) {
        check_round_trip_and_mutations(&message, &edits)?;
    }

    /// What a worker sends is checked before the server takes anything from it: the check never
    /// panics, and columns that pass it join a session's columns (at any offset, any rows kept)
    /// into columns that pass it too.
    #[test]
    fn step_results_are_checked_and_what_passes_joins_a_session_safely(
        result in step_result(),
        edits in edits(),
        offset in 0usize..8,
        dropped in 0usize..8,
    ) {
        let framed = protocol::encode(&Response::Stepped(result)).unwrap();
        for body in [framed[4..].to_vec(), mutate(framed[4..].to_vec(), &edits)] {
            let Ok(Response::Stepped(result)) = protocol::decode::<Response>(&body) else { continue };
            let envs = result.rewards.len();
            if result.check(envs).is_err() {
                continue;
            }
            let mut session = Infos::default();
            session.append(&result.step_infos, 0, |_| true);
            session.append(&result.reset_infos, offset, |local| local != dropped);
            prop_assert!(session.check(envs + offset).is_ok(), "{:?}", session);
        }
    }

    #[test]
    fn framed_streams_of_any_bytes_end_in_messages_or_a_clean_error(
        messages in prop::collection::vec(request(), 0..3),
        header in any::<[u8; 4]>(),
        tail in prop::collection::vec(any::<u8>(), 0..64),
    ) {
        let mut wire = Vec::new();
        for message in &messages {
            protocol::write_blocking(&mut wire, message).unwrap();
        }
        wire.extend_from_slice(&header);
        wire.extend_from_slice(&tail);
        let mut reader = wire.as_slice();
        for message in &messages {
            let read = protocol::read_blocking::<Request>(&mut reader).unwrap();
            prop_assert_eq!(read.map(|m| protocol::encode(&m).unwrap()), Some(protocol::encode(message).unwrap()));
        }
        // Then a length from the fuzzer: refused above the limit, a short body is an error, and
        // nothing panics.
        let length = u32::from_le_bytes(header) as usize;
        match protocol::read_blocking::<Request>(&mut reader) {
            Ok(Some(_)) => prop_assert!(length <= tail.len()),
            Ok(None) => prop_assert!(false, "a header was there to read"),
            Err(_) => {}
        }
        prop_assert_eq!(protocol::check_length(header).is_ok(), length <= MAX_MESSAGE_BYTES);
    }
}
