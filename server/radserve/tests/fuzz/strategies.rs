//! Strategies of the RPC fuzzer (`tests/fuzz.rs`): field values a careless or hostile client might
//! send, weighted towards the edges, and the operations a case is a sequence of.

use std::collections::HashMap;

use proptest::prelude::*;
use radserve_service::proto;

pub fn edge_u32() -> impl Strategy<Value = u32> {
    prop_oneof![3 => 0u32..10, 1 => 10u32..5000, 1 => prop::sample::select(vec![u32::MAX, u32::MAX - 1, 1 << 16, 1 << 31, 64 << 10, 128 << 20])]
}

pub fn edge_u64() -> impl Strategy<Value = u64> {
    prop_oneof![3 => 0u64..10, 1 => 10u64..100_000, 1 => any::<u64>(), 1 => prop::sample::select(vec![u64::MAX, 1 << 40, (1 << 40) + 1, 409_927_646_082_434_480])]
}

pub fn edge_f64() -> impl Strategy<Value = f64> {
    prop_oneof![2 => -2.0f64..100.0, 1 => prop::sample::select(vec![0.0, -0.0, f64::NAN, f64::INFINITY, f64::NEG_INFINITY, f64::MAX, f64::MIN_POSITIVE, 1e300])]
}

pub fn text(plausible: Vec<&'static str>) -> impl Strategy<Value = String> {
    prop_oneof![
        6 => prop::sample::select(plausible).prop_map(str::to_owned),
        1 => "\\PC{0,24}",
        1 => (1usize..4).prop_map(|k| "x".repeat(250 * k)),
        1 => Just("é".repeat(200)),
    ]
}

pub fn env_id() -> impl Strategy<Value = String> {
    text(vec![
        "gym/CartPole-v1", "gym/CartPole-v1", "gym/Pendulum-v1", "gym/MountainCarContinuous-v0", "gym/Acrobot-v1",
        "procgen/bigfish", "dmc/cartpole-balance", "gym/CartPole-v2", "gym/", "dmc", "", "GYM/cartpole-v1",
    ])
}

pub fn option_value() -> impl Strategy<Value = proto::OptionValue> {
    use proto::option_value::Value;
    let value = prop_oneof![
        any::<bool>().prop_map(Value::BoolValue),
        prop_oneof![-3i64..40, any::<i64>(), Just(i64::MAX), Just(1 << 40)].prop_map(Value::IntValue),
        edge_f64().prop_map(Value::FloatValue),
        text(vec!["easy", "hard", "fast", "default", "memory", ""]).prop_map(Value::StringValue),
    ];
    prop::option::weighted(0.95, value).prop_map(|value| proto::OptionValue { value })
}

pub fn options() -> impl Strategy<Value = HashMap<String, proto::OptionValue>> {
    let name = text(vec![
        "frame_stack", "action_repeat", "max_episode_steps", "pixels", "height", "width", "camera_id", "render_profile",
        "num_levels", "distribution_mode", "start_level", "use_backgrounds", "nonexistent",
    ]);
    prop::collection::hash_map(name, option_value(), 0..4)
}

pub fn stage_text() -> impl Strategy<Value = String> {
    text(vec![
        "crop(84)", "crop(2)", "translate(12)", "translate(2700)", "center_crop(84)", "center_translate(108)", "grayscale",
        "cutout(1,3)", "flip(p=0.5)", "rotate", "conv", "color_jitter", "noise(std=0.1)", "ras_s", "ras_m(alpha=2,beta=1)",
        "crop(size=-1)", "crpo", "none", "", "shift(4)", "shift(200)", "intensity", "intensity(0.9)",
    ])
}

/// Named views: mostly none, else a few plausible ones (DrQ's, CURL's, SVEA's), names and labels
/// that are not allowed, unknown `of` values and more views than allowed.
pub fn views() -> impl Strategy<Value = Vec<proto::SampleView>> {
    use proto::sample_view::Augmentation;
    let view = (
        text(vec!["obs", "obs_aug", "next_obs", "next_obs_aug", "anchor", "positive", "reward", "Obs", "obs-aug", "_x", ""]),
        prop_oneof![4 => 0i32..3, 1 => any::<i32>()],
        prop::option::of(stage_text().prop_map(Augmentation::PipelineText)),
        text(vec!["", "", "a", "b"]),
    )
        .prop_map(|(name, of, augmentation, draws)| proto::SampleView { name, of, augmentation, draws });
    prop_oneof![
        3 => Just(Vec::new()),
        2 => prop::collection::vec(view, 1..5),
        1 => prop::collection::vec(
            (text(vec!["v"]), 0i32..3).prop_map(|(name, of)| proto::SampleView { name, of, ..Default::default() }),
            8..12
        ),
    ]
}

pub fn pipeline() -> impl Strategy<Value = Option<proto::sample_batches_request::Augmentation>> {
    use proto::sample_batches_request::Augmentation;
    let typed = prop::collection::vec(
        (
            text(vec!["ras_s", "ras_m", "noise", "crop", "translate", "conv", "std=1)|noise(std", ""]),
            prop::collection::hash_map(text(vec!["alpha", "beta", "std", "size", "p", "x"]), edge_f64(), 0..3),
        )
            .prop_map(|(name, args)| proto::AugmentationStage { name, args }),
        0..10,
    );
    prop_oneof![
        2 => Just(None),
        3 => prop::collection::vec(stage_text(), 0..10).prop_map(|stages| Some(Augmentation::PipelineText(stages.join("|")))),
        2 => typed.prop_map(|stages| Some(Augmentation::Pipeline(proto::AugmentationPipeline { stages }))),
    ]
}

pub fn tensor() -> impl Strategy<Value = proto::Tensor> {
    let dtype = prop_oneof![4 => 0i32..7, 1 => any::<i32>()];
    let shape = prop::collection::vec(prop_oneof![4 => 0i64..4, 1 => any::<i64>(), 1 => Just(-1i64)], 0..4);
    (dtype, shape, any::<u8>(), prop::collection::vec(any::<u8>(), 0..40)).prop_map(|(dtype, shape, fill, data)| {
        // Often exactly the bytes the shape and dtype need, so validation gets past the size check.
        let size = match dtype {
            1 | 6 => 1,
            2 | 4 => 4,
            3 | 5 => 8,
            _ => 1,
        };
        let elements = shape.iter().try_fold(1u64, |total, &d| u64::try_from(d).ok().and_then(|d| total.checked_mul(d)));
        let data = match elements.map(|e| e * size) {
            Some(bytes) if bytes <= 256 && fill % 2 == 0 => vec![fill; bytes as usize],
            _ => data,
        };
        proto::Tensor { dtype, shape, data: data.into() }
    })
}

/// Which session a request names: one of the live ones (base or created in this case) or not.
#[derive(Clone, Debug)]
pub enum Target {
    Live(usize),
    Id(String),
}

pub fn target() -> impl Strategy<Value = Target> {
    prop_oneof![
        5 => any::<usize>().prop_map(Target::Live),
        1 => text(vec!["", "0", "s-0000000000000000", "../../etc/passwd"]).prop_map(Target::Id),
    ]
}

pub fn sample_request() -> impl Strategy<Value = proto::SampleBatchesRequest> {
    (
        (edge_u32(), pipeline(), prop_oneof![4 => 0i32..3, 1 => any::<i32>()], edge_u32(), any::<u64>()),
        (prop::option::of(edge_u64()), prop::option::of(edge_f64()), edge_f64(), prop::option::of(0u64..6)),
        (edge_u32(), prop_oneof![4 => 0i32..2, 1 => any::<i32>()], edge_u32(), any::<bool>(), prop::option::of(any::<bool>())),
        (views(), prop::option::of(prop_oneof![3 => 0u32..6, 1 => edge_u32()]), prop::option::of(edge_f64())),
        (prop_oneof![4 => 0i32..2, 1 => any::<i32>()], prop::option::of(edge_f64()), prop::option::of(edge_f64())),
        prop::option::of((
            prop_oneof![3 => 0u32..12, 1 => edge_u32()],
            prop_oneof![3 => 0u32..4, 1 => edge_u32()],
            prop_oneof![3 => 0u32..4, 1 => edge_u32()],
            prop_oneof![4 => 0i32..2, 1 => any::<i32>()],
        )),
    )
        .prop_map(
            |(
                (batch_size, augmentation, sharing, prefetch, seed),
                (min_size, samples_per_insert, error_buffer, max_batches),
                (chunk_bytes, source, epochs, per_env_augmentation, include_next_obs),
                (views, n_step, discount),
                (sampler, priority_exponent, importance_sampling_exponent),
                sequence,
            )| proto::SampleBatchesRequest {
                session_id: String::new(),
                batch_size,
                augmentation,
                sharing,
                prefetch,
                seed,
                min_size,
                samples_per_insert,
                error_buffer,
                max_batches,
                chunk_bytes,
                source,
                epochs,
                per_env_augmentation,
                include_next_obs,
                views,
                n_step,
                discount,
                sampler,
                priority_exponent,
                importance_sampling_exponent,
                sequence: sequence.map(|(length, burn_in, period, boundary)| proto::SequenceRequest { length, burn_in, period, boundary }),
            },
        )
}

/// What the client does with a shared-stepping channel it was given.
#[derive(Clone, Debug)]
pub enum ChannelUse {
    /// Never connects (the server gives up after its connect timeout).
    Leave,
    /// Connects, presents the token (or a wrong one) and sends raw 16-byte requests.
    Connect { right_token: bool, requests: Vec<[u8; 16]> },
}

#[derive(Clone, Debug)]
pub enum Op {
    ListEnvs(String),
    Create(proto::CreateSessionRequest),
    Describe(Target),
    Close(Target),
    ListSessions,
    Reset(Target, Option<u64>),
    Step(Target, proto::Tensor),
    Act(Target, Vec<Option<Result<Option<u64>, proto::Tensor>>>),
    ShareActing(Target, ChannelUse),
    Sample(Target, proto::SampleBatchesRequest),
    SampleShared(Target, proto::SampleBatchesRequest, Vec<u64>, bool),
    AsyncReset(Target, Option<u64>),
    Send(Target, proto::Tensor, Vec<u32>),
    Recv(Target, Option<(proto::Tensor, Vec<u32>)>),
    SetPolicy(Target, PolicyModel, i32, u32),
    StartActing(Target, proto::StartActingRequest),
    StopActing(Target),
    UpdatePriorities(Target, Vec<u64>, Vec<f64>),
}

/// A SetPolicy's model: a fixture (server/policy/tests/models), one with bytes changed, or anything.
#[derive(Clone, Debug)]
pub enum PolicyModel {
    Fixture(usize),
    Damaged(usize, Vec<(usize, u8)>),
    Bytes(Vec<u8>),
}

pub const POLICY_FIXTURES: &[&str] = &[
    "categorical_cartpole.onnx",
    "gaussian_pendulum.onnx",
    "categorical_fake.onnx",
    "nan_fake.onnx",
    "random_op_fake.onnx",
    "external_fake.onnx",
    "gaussian_3x2.onnx",
];

pub fn policy_model() -> impl Strategy<Value = PolicyModel> {
    prop_oneof![
        4 => (0..POLICY_FIXTURES.len()).prop_map(PolicyModel::Fixture),
        2 => (0..POLICY_FIXTURES.len(), prop::collection::vec((any::<usize>(), any::<u8>()), 1..6))
            .prop_map(|(index, flips)| PolicyModel::Damaged(index, flips)),
        1 => prop::collection::vec(any::<u8>(), 0..256).prop_map(PolicyModel::Bytes),
    ]
}

pub fn start_acting() -> impl Strategy<Value = proto::StartActingRequest> {
    (
        prop::option::of(edge_f64()),
        edge_u64(),
        any::<bool>(),
        prop::option::of(edge_f64()),
        edge_f64(),
        edge_u64(),
        prop::option::of(any::<u64>()),
        (prop::option::of(edge_u64()), prop::option::of(edge_u64())),
    )
        .prop_map(|(steps_per_second, random_steps, eval, samples_per_insert, error_buffer, min_size, seed, (max_episodes, max_env_steps))| {
            proto::StartActingRequest {
                session_id: String::new(),
                steps_per_second,
                random_steps,
                eval,
                samples_per_insert,
                error_buffer,
                min_size,
                seed,
                max_episodes,
                max_env_steps,
            }
        })
}

pub fn channel_use() -> impl Strategy<Value = ChannelUse> {
    let request = prop_oneof![
        // A kind, a seed flag, flags, zeros, a seed: well-formed, then anything.
        (prop::sample::select(vec![b'S', b'R', b'A', b'E', b'V']), 0u8..3, 0u8..4, any::<u64>()).prop_map(|(kind, flag, flags, seed)| {
            let mut request = [0u8; 16];
            request[0] = kind;
            request[1] = flag;
            request[2] = flags;
            request[8..].copy_from_slice(&seed.to_le_bytes());
            request
        }),
        any::<[u8; 16]>(),
    ];
    prop_oneof![
        1 => Just(ChannelUse::Leave),
        4 => (any::<bool>(), prop::collection::vec(request, 0..4))
            .prop_map(|(wrong, requests)| ChannelUse::Connect { right_token: !wrong, requests }),
    ]
}

/// Env ids of a send: mostly small (a live session's), some far out.
pub fn env_ids() -> impl Strategy<Value = Vec<u32>> {
    prop::collection::vec(prop_oneof![4 => 0u32..3, 1 => any::<u32>()], 0..4)
}

pub fn op() -> impl Strategy<Value = Op> {
    let create = (
        env_id(),
        prop_oneof![3 => 0u32..4, 1 => edge_u32()],
        any::<u64>(),
        options(),
        prop::option::of((edge_u64(), edge_u32()).prop_map(|(capacity, rollout_steps)| proto::ReplayOptions { capacity, rollout_steps })),
        prop_oneof![3 => Just(String::new()), 1 => stage_text()],
        // Names: none, a few that repeat (ALREADY_EXISTS while their session lives), anything.
        prop_oneof![3 => Just(String::new()), 2 => "run-[0-2]", 1 => any::<String>()],
    )
        .prop_map(|(env_id, num_envs, seed, options, replay, observation_view, name)| proto::CreateSessionRequest {
            env_id,
            num_envs,
            seed,
            options,
            replay,
            observation_view,
            name,
        });
    let act_message = prop_oneof![
        1 => Just(None),
        2 => prop::option::of(edge_u64()).prop_map(|seed| Some(Ok(seed))),
        3 => tensor().prop_map(|actions| Some(Err(actions))),
    ];
    prop_oneof![
        1 => text(vec!["", "gym/", "dmc/", "procgen/big", "zzz"]).prop_map(Op::ListEnvs),
        4 => create.prop_map(Op::Create),
        1 => target().prop_map(Op::Describe),
        2 => target().prop_map(Op::Close),
        1 => Just(Op::ListSessions),
        2 => (target(), prop::option::of(edge_u64())).prop_map(|(t, seed)| Op::Reset(t, seed)),
        4 => (target(), tensor()).prop_map(|(t, actions)| Op::Step(t, actions)),
        2 => (target(), prop::collection::vec(act_message, 0..4)).prop_map(|(t, messages)| Op::Act(t, messages)),
        2 => (target(), channel_use()).prop_map(|(t, how)| Op::ShareActing(t, how)),
        4 => (target(), sample_request()).prop_map(|(t, r)| Op::Sample(t, r)),
        2 => (target(), sample_request(), prop::collection::vec(edge_u64(), 0..3), any::<bool>())
            .prop_map(|(t, r, releases, release_first)| Op::SampleShared(t, r, releases, release_first)),
        1 => (target(), prop::option::of(edge_u64())).prop_map(|(t, seed)| Op::AsyncReset(t, seed)),
        2 => (target(), tensor(), env_ids()).prop_map(|(t, actions, ids)| Op::Send(t, actions, ids)),
        2 => (target(), prop::option::of((tensor(), env_ids()))).prop_map(|(t, send)| Op::Recv(t, send)),
        2 => (target(), policy_model(), prop_oneof![4 => 1i32..4, 1 => any::<i32>()], edge_u32())
            .prop_map(|(t, model, head, version)| Op::SetPolicy(t, model, head, version)),
        2 => (target(), start_acting()).prop_map(|(t, request)| Op::StartActing(t, request)),
        1 => target().prop_map(Op::StopActing),
        2 => (target(), prop::collection::vec(edge_u64(), 0..4), prop::collection::vec(edge_f64(), 0..4))
            .prop_map(|(t, keys, priorities)| Op::UpdatePriorities(t, keys, priorities)),
    ]
}

