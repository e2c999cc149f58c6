//! Conversions between proto messages and core types.

use std::collections::HashMap;
use std::sync::Arc;

use radserve_augment::{Pipeline, Sharing, TransitionPart};
use radserve_replay::{Batch, Boundary, Prioritized, ReplayError, Returns, SampleSpec, Sequence, Slot, Source, ViewSpec, MAX_VIEWS};
use radserve_core::{
    BufferRequest, CatalogEntry, DType, EpisodeEnd, InfoKind, Infos, OptionValue, Options, SessionInfo, SessionSummary, Space,
    StepOutcome,
};

use crate::error::{Result, ServiceError};
use crate::proto;

pub fn dtype_to_proto(dtype: DType) -> proto::DType {
    match dtype {
        DType::Uint8 => proto::DType::DtypeUint8,
        DType::Int32 => proto::DType::DtypeInt32,
        DType::Int64 => proto::DType::DtypeInt64,
        DType::Float32 => proto::DType::DtypeFloat32,
        DType::Float64 => proto::DType::DtypeFloat64,
        DType::Bool => proto::DType::DtypeBool,
    }
}

pub fn dtype_from_proto(raw: i32) -> Result<DType> {
    match proto::DType::try_from(raw) {
        Ok(proto::DType::DtypeUint8) => Ok(DType::Uint8),
        Ok(proto::DType::DtypeInt32) => Ok(DType::Int32),
        Ok(proto::DType::DtypeInt64) => Ok(DType::Int64),
        Ok(proto::DType::DtypeFloat32) => Ok(DType::Float32),
        Ok(proto::DType::DtypeFloat64) => Ok(DType::Float64),
        Ok(proto::DType::DtypeBool) => Ok(DType::Bool),
        Ok(proto::DType::DtypeUnspecified) | Err(_) => {
            Err(ServiceError::BadRequest(format!("tensor dtype {raw} is not one of the DType values")))
        }
    }
}

pub fn space_to_proto(space: &Space) -> proto::Space {
    let kind = match space {
        Space::Box { dtype, shape, low, high } => proto::space::Kind::Box(proto::BoxSpace {
            dtype: dtype_to_proto(*dtype) as i32,
            shape: shape.iter().map(|&d| d as i64).collect(),
            low: low.clone(),
            high: high.clone(),
        }),
        Space::Discrete { n } => proto::space::Kind::Discrete(proto::DiscreteSpace { n: *n }),
    };
    proto::Space { kind: Some(kind) }
}

pub fn option_to_proto(value: &OptionValue) -> proto::OptionValue {
    use proto::option_value::Value;
    let value = match value {
        OptionValue::Bool(v) => Value::BoolValue(*v),
        OptionValue::Int(v) => Value::IntValue(*v),
        OptionValue::Float(v) => Value::FloatValue(*v),
        OptionValue::Str(v) => Value::StringValue(v.clone()),
    };
    proto::OptionValue { value: Some(value) }
}

pub fn options_to_proto(options: &Options) -> HashMap<String, proto::OptionValue> {
    options.iter().map(|(name, value)| (name.clone(), option_to_proto(value))).collect()
}

pub fn options_from_proto(options: &HashMap<String, proto::OptionValue>) -> Result<Options> {
    use proto::option_value::Value;
    options
        .iter()
        .map(|(name, value)| {
            let value = match &value.value {
                Some(Value::BoolValue(v)) => OptionValue::Bool(*v),
                Some(Value::IntValue(v)) => OptionValue::Int(*v),
                Some(Value::FloatValue(v)) => OptionValue::Float(*v),
                Some(Value::StringValue(v)) => OptionValue::Str(v.clone()),
                None => return Err(ServiceError::BadRequest(format!("option '{name}' has no value"))),
            };
            Ok((name.clone(), value))
        })
        .collect()
}

pub fn catalog_entry_to_proto(entry: &CatalogEntry) -> proto::EnvInfo {
    let (observation_space, action_space) = match &entry.spaces {
        Ok((observation, action)) => (Some(space_to_proto(observation)), Some(space_to_proto(action))),
        Err(_) => (None, None),
    };
    proto::EnvInfo {
        id: entry.id.full(),
        family: entry.id.family.prefix().to_string(),
        observation_space,
        action_space,
        default_options: options_to_proto(&entry.default_options),
    }
}

pub fn session_info_to_proto(info: &SessionInfo) -> proto::SessionInfo {
    proto::SessionInfo {
        session_id: info.session_id.clone(),
        env_id: info.env_id.clone(),
        num_envs: info.num_envs as u32,
        seed: info.seed,
        options: options_to_proto(&info.options),
        observation_space: Some(space_to_proto(&info.observation_space)),
        action_space: Some(space_to_proto(&info.action_space)),
        frame_stack: info.frame_stack as u32,
        autoreset_mode: info.autoreset_mode.name().to_string(),
        total_env_steps: info.total_env_steps,
        episodes_completed: info.episodes_completed,
        replay: info.replay.as_ref().map(|replay| proto::ReplayInfo {
            capacity: replay.capacity as u64,
            size: replay.size as u64,
            inserts: replay.inserts,
            samples: replay.samples,
            batches: replay.batches,
            batches_per_second: replay.batches_per_second,
            memory_bytes: replay.memory_bytes,
            frames_per_transition: replay.frames_per_transition,
            active_streams: replay.active_streams as u32,
            rollout_steps: replay.rollout_steps.unwrap_or(0) as u32,
            snapshot: replay.snapshot.as_ref().map(|snapshot| proto::ReplaySnapshot {
                restored_transitions: snapshot.restored_transitions,
                disk_bytes: snapshot.disk_bytes,
                age_seconds: snapshot.age.map(|age| age.as_secs_f64()),
                pending_frames: snapshot.pending_frames,
            }),
        }),
        name: info.name.clone().unwrap_or_default(),
        acting: info.acting.as_ref().map(acting_to_proto),
    }
}

pub fn acting_to_proto(status: &radserve_core::ActingStatus) -> proto::ActingInfo {
    proto::ActingInfo {
        state: status.state.name().to_string(),
        policy_version: status.policy_version,
        acting_version: status.acting_version,
        head: status.head.clone().unwrap_or_default(),
        env_steps: status.env_steps,
        episodes: status.episodes,
        recent_returns: status.recent_returns.clone(),
        recent_envs: status.recent_envs.clone(),
        inference_seconds: status.inference_seconds,
        step_seconds: status.step_seconds,
        limited_seconds: status.limited_seconds,
        error: status.error.clone().unwrap_or_default(),
    }
}

/// The head a SetPolicy names, with its noise schedule (DrQ-v2's defaults when unset).
pub fn policy_head(head: i32, noise: Option<&proto::NoiseSchedule>) -> Result<radserve_policy::Head> {
    use radserve_policy::Head;
    match proto::PolicyHead::try_from(head) {
        Ok(proto::PolicyHead::GaussianTanh) => Ok(Head::GaussianTanh),
        Ok(proto::PolicyHead::Categorical) => Ok(Head::Categorical),
        Ok(proto::PolicyHead::DeterministicNoise) => {
            let noise = noise.copied().unwrap_or(proto::NoiseSchedule { std_start: 1.0, std_end: 0.1, std_steps: 500_000, clip: 0.3 });
            let finite = [noise.std_start, noise.std_end, noise.clip].iter().all(|value| value.is_finite() && *value >= 0.0);
            if !finite {
                return Err(ServiceError::BadRequest(format!(
                    "noise std_start, std_end and clip must be finite and at least 0; got {}, {}, {}",
                    noise.std_start, noise.std_end, noise.clip
                )));
            }
            Ok(Head::DeterministicNoise { std_start: noise.std_start, std_end: noise.std_end, std_steps: noise.std_steps, clip: noise.clip })
        }
        Ok(proto::PolicyHead::Unspecified) | Err(_) => Err(ServiceError::BadRequest(format!(
            "head must be POLICY_HEAD_GAUSSIAN_TANH, POLICY_HEAD_CATEGORICAL or POLICY_HEAD_DETERMINISTIC_NOISE; got {head}"
        ))),
    }
}

pub fn session_summary_to_proto(summary: &SessionSummary) -> proto::SessionSummary {
    proto::SessionSummary {
        session_id: summary.session_id.clone(),
        env_id: summary.env_id.clone(),
        num_envs: summary.num_envs as u32,
        memory_bytes: summary.memory_bytes,
        idle_seconds: summary.idle.as_secs_f64(),
        open_streams: summary.open_streams as u32,
        age_seconds: summary.age.as_secs_f64(),
        owner: summary.owner.clone(),
        name: summary.name.clone().unwrap_or_default(),
    }
}

/// What a ResetRequest resets: empty repeated fields mean "not given".
pub fn reset_spec(request: &proto::ResetRequest) -> radserve_core::ResetSpec {
    radserve_core::ResetSpec {
        seed: request.seed,
        env_seeds: (!request.env_seeds.is_empty()).then(|| request.env_seeds.clone()),
        mask: (!request.mask.is_empty()).then(|| request.mask.clone()),
    }
}

/// The buffer a CreateSession asks for: a rollout when rollout_steps is set, else replay when
/// capacity is (zero capacity: none).
pub fn buffer_request(options: Option<&proto::ReplayOptions>) -> Option<BufferRequest> {
    let options = options?;
    if options.rollout_steps > 0 {
        return Some(BufferRequest::Rollout { steps: options.rollout_steps as usize });
    }
    (options.capacity > 0).then_some(BufferRequest::Replay { capacity: options.capacity as usize })
}

/// Default largest chunk of tensor bytes per BatchChunk: a Python client takes 1-4 MB messages
/// fastest (measured; one 32 MB message is ~40% slower).
pub const DEFAULT_CHUNK_BYTES: usize = 2 << 20;

/// The smallest chunk a client may ask for. Each chunk is a message with its own header, field
/// name and shape (~100 bytes plus tonic's per-message buffers): 1-byte chunks cost the server ~200
/// bytes of memory per tensor byte.
pub const MIN_CHUNK_BYTES: usize = 64 << 10;

/// The chunk size a SampleBatches request asks for (0: the default), within
/// [`MIN_CHUNK_BYTES`, `crate::MAX_MESSAGE_BYTES` / 2].
pub fn chunk_bytes(requested: u32) -> Result<usize> {
    let max = crate::MAX_MESSAGE_BYTES / 2;
    match requested as usize {
        0 => Ok(DEFAULT_CHUNK_BYTES),
        bytes if (MIN_CHUNK_BYTES..=max).contains(&bytes) => Ok(bytes),
        bytes => Err(ServiceError::BadRequest(format!(
            "chunk_bytes must be 0 (the default, {DEFAULT_CHUNK_BYTES}) or between {MIN_CHUNK_BYTES} and {max}, got {bytes}"
        ))),
    }
}

/// A typed pipeline's stages in the text form, every name and key checked to be a plain name first
/// (so that no key can carry text that the parser would read as more stages or arguments).
fn typed_pipeline_text(typed: &proto::AugmentationPipeline) -> Result<String> {
    use radserve_core::bounds::clip;
    let plain = |text: &str| !text.is_empty() && text.len() <= 32 && text.chars().all(|c| c.is_ascii_alphanumeric() || c == '_');
    if typed.stages.len() > radserve_augment::MAX_STAGES {
        return Err(ServiceError::BadRequest(format!(
            "a pipeline has at most {} stages, got {}",
            radserve_augment::MAX_STAGES,
            typed.stages.len()
        )));
    }
    let mut stages = Vec::with_capacity(typed.stages.len());
    for stage in &typed.stages {
        if !plain(&stage.name) {
            return Err(ServiceError::BadRequest(format!(
                "augmentation stage names are plain names such as \"crop\", got {:?}",
                clip(&stage.name)
            )));
        }
        if let Some(key) = stage.args.keys().find(|key| !plain(key)) {
            return Err(ServiceError::BadRequest(format!(
                "argument names of {} are plain names such as \"size\", got {:?}",
                stage.name,
                clip(key)
            )));
        }
        let mut args: Vec<_> = stage.args.iter().collect();
        args.sort_by(|a, b| a.0.cmp(b.0));
        let args: Vec<String> = args.iter().map(|(key, value)| format!("{key}={value}")).collect();
        stages.push(format!("{}({})", stage.name, args.join(",")));
    }
    Ok(stages.join("|"))
}

/// A pipeline given typed or as text (none: no augmentation).
fn pipeline_from_proto(text: Option<&str>, typed: Option<&proto::AugmentationPipeline>) -> Result<Pipeline> {
    Ok(match (text, typed) {
        (Some(text), _) => Pipeline::parse(text).map_err(ReplayError::from)?,
        // The typed form goes through the text form's parser, so both are checked the same way.
        (None, Some(typed)) => Pipeline::parse(&typed_pipeline_text(typed)?).map_err(ReplayError::from)?,
        (None, None) => Pipeline::identity(),
    })
}

/// A request's named views, bounded before any is parsed; names and shapes are checked by the
/// producer against the observation.
fn views_from_proto(request: &proto::SampleBatchesRequest) -> Result<Vec<ViewSpec>> {
    use proto::sample_view::Augmentation as Choice;
    use radserve_core::bounds::clip;
    if request.views.is_empty() {
        return Ok(Vec::new());
    }
    if request.views.len() > MAX_VIEWS {
        return Err(ServiceError::BadRequest(format!("views: at most {MAX_VIEWS} per request, got {}", request.views.len())));
    }
    let beside = |field: &str| {
        Err(ServiceError::BadRequest(format!(
            "{field} applies to obs and next_obs when no views are named; with views, give each view its own pipeline \
             (and a `draws` label to share draws, a view of next_obs for next observations)"
        )))
    };
    if request.augmentation.is_some() {
        return beside("augmentation");
    }
    if request.sharing != proto::DrawSharing::Reference as i32 {
        return beside("sharing");
    }
    if request.include_next_obs.is_some() {
        return beside("include_next_obs");
    }
    request
        .views
        .iter()
        .map(|view| {
            let of = match proto::ViewOf::try_from(view.of) {
                Ok(proto::ViewOf::Obs) => TransitionPart::Obs,
                Ok(proto::ViewOf::NextObs) => TransitionPart::NextObs,
                Ok(proto::ViewOf::Unspecified) if view.name.starts_with("next_") => TransitionPart::NextObs,
                Ok(proto::ViewOf::Unspecified) => TransitionPart::Obs,
                Err(_) => {
                    return Err(ServiceError::BadRequest(format!(
                        "view {:?}: `of` must be VIEW_OF_OBS or VIEW_OF_NEXT_OBS (the fields a transition has), got {}",
                        clip(&view.name),
                        view.of
                    )))
                }
            };
            let (text, typed) = match &view.augmentation {
                Some(Choice::PipelineText(text)) => (Some(text.as_str()), None),
                Some(Choice::Pipeline(typed)) => (None, Some(typed)),
                None => (None, None),
            };
            let pipeline = pipeline_from_proto(text, typed)
                .map_err(|error| ServiceError::BadRequest(format!("view {:?}: {error}", clip(&view.name))))?;
            if view.draws.len() > radserve_replay::MAX_VIEW_NAME {
                return Err(ServiceError::BadRequest(format!(
                    "view {:?}: a draws label has at most {} characters, got {}",
                    clip(&view.name),
                    radserve_replay::MAX_VIEW_NAME,
                    view.draws.len()
                )));
            }
            let draws = (!view.draws.is_empty()).then(|| view.draws.clone());
            Ok(ViewSpec { name: view.name.clone(), of, pipeline, draws })
        })
        .collect()
}

/// A request's n-step returns (none: neither n_step nor discount given).
fn returns_from_proto(request: &proto::SampleBatchesRequest) -> Result<Option<Returns>> {
    let n_step = request.n_step.unwrap_or(1) as usize;
    match request.discount {
        None if n_step > 1 => Err(ServiceError::BadRequest(format!(
            "n_step {n_step} needs the discount its rewards are summed with (discount, in [0, 1])"
        ))),
        None if request.n_step.is_some() => Ok(Some(Returns::new(n_step, 1.0).map_err(ServiceError::from)?)),
        None => Ok(None),
        Some(discount) => Ok(Some(Returns::new(n_step, discount).map_err(ServiceError::from)?)),
    }
}

/// A request's sampler: None for uniform; the exponents only with SAMPLER_PRIORITIZED.
fn prioritized_from_proto(request: &proto::SampleBatchesRequest) -> Result<Option<Prioritized>> {
    match proto::Sampler::try_from(request.sampler) {
        Ok(proto::Sampler::Uniform) => {
            for (name, value) in
                [("priority_exponent", request.priority_exponent), ("importance_sampling_exponent", request.importance_sampling_exponent)]
            {
                if value.is_some() {
                    return Err(ServiceError::BadRequest(format!(
                        "{name} applies to sampler SAMPLER_PRIORITIZED; this request samples uniformly"
                    )));
                }
            }
            Ok(None)
        }
        Ok(proto::Sampler::Prioritized) => Ok(Some(
            Prioritized::new(
                request.priority_exponent.unwrap_or(DEFAULT_PRIORITY_EXPONENT),
                request.importance_sampling_exponent.unwrap_or(DEFAULT_IMPORTANCE_SAMPLING_EXPONENT),
            )
            .map_err(ServiceError::from)?,
        )),
        Err(_) => Err(ServiceError::BadRequest(format!(
            "sampler must be SAMPLER_UNIFORM (0) or SAMPLER_PRIORITIZED (1), got {}",
            request.sampler
        ))),
    }
}

/// A request's sequence (none: single transitions), its bounds checked.
fn sequence_from_proto(request: &proto::SampleBatchesRequest) -> Result<Option<Sequence>> {
    let Some(sequence) = &request.sequence else { return Ok(None) };
    let boundary = match proto::SequenceBoundary::try_from(sequence.boundary) {
        Ok(proto::SequenceBoundary::WithinEpisode) => Boundary::WithinEpisode,
        Ok(proto::SequenceBoundary::AcrossEpisodes) => Boundary::AcrossEpisodes,
        Err(_) => {
            return Err(ServiceError::BadRequest(format!(
                "sequence.boundary must be SEQUENCE_BOUNDARY_WITHIN_EPISODE (0) or SEQUENCE_BOUNDARY_ACROSS_EPISODES (1), got {}",
                sequence.boundary
            )))
        }
    };
    let period = if sequence.period == 0 { 1 } else { sequence.period as usize };
    Ok(Some(Sequence::new(sequence.length as usize, sequence.burn_in as usize, period, boundary).map_err(ServiceError::from)?))
}

/// Schaul et al.'s proportional variant: alpha 0.6, beta from 0.4.
pub const DEFAULT_PRIORITY_EXPONENT: f64 = 0.6;
pub const DEFAULT_IMPORTANCE_SAMPLING_EXPONENT: f64 = 0.4;

/// A SampleBatches request as the producer's spec, every field checked; a field the request leaves
/// at its proto3 zero gets the default the proto documents.
pub fn sample_spec_from_proto(request: &proto::SampleBatchesRequest) -> Result<SampleSpec> {
    use proto::sample_batches_request::Augmentation as Choice;
    let pipeline = match &request.augmentation {
        None => Pipeline::identity(),
        Some(Choice::PipelineText(text)) => pipeline_from_proto(Some(text), None)?,
        Some(Choice::Pipeline(typed)) => pipeline_from_proto(None, Some(typed))?,
    };
    let sharing = match proto::DrawSharing::try_from(request.sharing) {
        Ok(proto::DrawSharing::Reference) => Sharing::Reference,
        Ok(proto::DrawSharing::Shared) => Sharing::Shared,
        Ok(proto::DrawSharing::Independent) => Sharing::Independent,
        Err(_) => return Err(ServiceError::BadRequest(format!("unknown DrawSharing value {}", request.sharing))),
    };
    let batch_size = request.batch_size as usize;
    let source = match proto::BatchSource::try_from(request.source) {
        Ok(proto::BatchSource::SourceReplay) => Source::Replay,
        Ok(proto::BatchSource::SourceRollout) => {
            let epochs = if request.epochs == 0 { SampleSpec::DEFAULT_EPOCHS } else { request.epochs as usize };
            Source::Rollout { epochs, per_env_draws: request.per_env_augmentation }
        }
        Err(_) => return Err(ServiceError::BadRequest(format!("unknown BatchSource value {}", request.source))),
    };
    let sequence = sequence_from_proto(request)?;
    // A sequence's next observations are its next steps: not sent unless asked for (and refused then).
    let include_next_obs = request.include_next_obs.unwrap_or(source == Source::Replay && sequence.is_none());
    let views = views_from_proto(request)?;
    let returns = returns_from_proto(request)?;
    let prioritized = prioritized_from_proto(request)?;
    Ok(SampleSpec {
        source,
        include_next_obs,
        batch_size,
        pipeline,
        sharing,
        views,
        returns,
        prioritized,
        sequence,
        seed: request.seed,
        prefetch: if request.prefetch == 0 { SampleSpec::DEFAULT_PREFETCH } else { request.prefetch as usize },
        min_size: if source == Source::Replay { request.min_size.map_or(batch_size, |size| size as usize) } else { 0 },
        samples_per_insert: request.samples_per_insert,
        error_buffer: request.error_buffer,
        max_batches: request.max_batches,
    })
}

/// An observation buffer shared between the chunks being sent and the stream, which takes it back
/// for the producer once every chunk is gone (no copy either way).
struct SharedBuffer(Arc<Vec<u8>>);

impl AsRef<[u8]> for SharedBuffer {
    fn as_ref(&self) -> &[u8] {
        &self.0
    }
}

/// The fields of a batch other than its observations, in the stream's order, as (name, dtype,
/// shape, little-endian bytes); `discount` only with n-step returns, `t` only for rollout batches.
fn small_fields(batch: &mut Batch, action: &Space) -> Vec<(String, proto::DType, Vec<i64>, Vec<u8>)> {
    // [batch] or, for sequences, [batch, steps]: the leading dimensions of every field.
    let lead = batch.lead_dims();
    let len = lead.iter().product::<usize>();
    let with_batch = |shape: &[usize]| -> Vec<i64> { lead.iter().chain(shape).map(|&d| d as i64).collect() };
    let rows = with_batch(&[]);
    let metadata = std::mem::take(&mut batch.metadata);
    let int32_bytes: Vec<u8> = metadata.env_indices.iter().flat_map(|v| (*v as i32).to_le_bytes()).collect();
    let int64_bytes: Vec<u8> = metadata.step_indices.iter().flat_map(|v| (*v as i64).to_le_bytes()).collect();
    let reward_bytes: Vec<u8> = metadata.rewards.iter().flat_map(|v| v.to_le_bytes()).collect();
    let mut fields = vec![
        ("action", dtype_to_proto(action.dtype()), with_batch(action.shape()), metadata.actions),
        ("reward", proto::DType::DtypeFloat32, rows.clone(), reward_bytes),
        ("terminated", proto::DType::DtypeUint8, rows.clone(), metadata.terminated),
        ("truncated", proto::DType::DtypeUint8, rows.clone(), metadata.truncated),
        ("env_index", proto::DType::DtypeInt32, rows.clone(), int32_bytes),
        ("step_index", proto::DType::DtypeInt64, rows.clone(), int64_bytes),
        ("policy_version", proto::DType::DtypeInt32, rows.clone(), metadata.policy_versions.iter().flat_map(|v| v.to_le_bytes()).collect()),
    ];
    if batch.has_discount {
        fields.push(("discount", proto::DType::DtypeFloat32, rows.clone(), metadata.discounts.iter().flat_map(|v| v.to_le_bytes()).collect()));
    }
    if batch.prioritized {
        fields.push(("key", proto::DType::DtypeInt64, rows.clone(), metadata.keys.iter().flat_map(|v| (*v as i64).to_le_bytes()).collect()));
        fields.push(("probability", proto::DType::DtypeFloat64, rows.clone(), metadata.probabilities.iter().flat_map(|v| v.to_le_bytes()).collect()));
        let table_size = (batch.table_size as i64).to_le_bytes();
        fields.push(("table_size", proto::DType::DtypeInt64, rows.clone(), table_size.repeat(len)));
        fields.push(("weight", proto::DType::DtypeFloat32, rows.clone(), metadata.weights.iter().flat_map(|v| v.to_le_bytes()).collect()));
    }
    if batch.sequence_steps.is_some() {
        for (name, flags) in [
            ("is_first", metadata.is_first),
            ("is_last", metadata.is_last),
            ("is_terminal", metadata.is_terminal),
            ("mask", metadata.mask),
        ] {
            fields.push((name, proto::DType::DtypeUint8, rows.clone(), flags));
        }
    }
    if let Some(rollout_t) = &batch.rollout_t {
        fields.push(("t", proto::DType::DtypeInt32, rows.clone(), rollout_t.iter().flat_map(|v| (*v as i32).to_le_bytes()).collect()));
        fields.push(("log_prob", proto::DType::DtypeFloat32, rows.clone(), metadata.log_probs.iter().flat_map(|v| v.to_le_bytes()).collect()));
        fields.push(("value", proto::DType::DtypeFloat32, rows.clone(), metadata.values.iter().flat_map(|v| v.to_le_bytes()).collect()));
    }
    fields.into_iter().map(|(name, dtype, shape, data)| (name.to_owned(), dtype, shape, data)).collect()
}

fn observation_dtype(batch: &Batch) -> proto::DType {
    if batch.obs_float32 {
        proto::DType::DtypeFloat32
    } else {
        proto::DType::DtypeUint8
    }
}

fn observation_shape(batch: &Batch, view: &radserve_replay::ViewData) -> Vec<i64> {
    batch.lead_dims().into_iter().chain(view.shape.iter().copied()).map(|d| d as i64).collect()
}

/// Split a batch into BatchChunk messages of at most `chunk_bytes` of tensor data each. The
/// observation buffers are sliced, never copied; they are also returned, for recycling once the
/// chunks have been sent (when the `Arc` is unique again).
pub fn batch_to_chunks(mut batch: Batch, action: &Space, chunk_bytes: usize) -> (Vec<proto::BatchChunk>, Vec<Arc<Vec<u8>>>) {
    let obs_dtype = observation_dtype(&batch);
    let views = std::mem::take(&mut batch.views);
    let small = small_fields(&mut batch, action);
    let view_count = views.len();
    let mut fields: Vec<_> = views
        .into_iter()
        .map(|view| {
            let shape = observation_shape(&batch, &view);
            (view.name, obs_dtype, shape, view.data)
        })
        .collect();
    fields.extend(small);
    let mut chunks = Vec::new();
    let mut observation_buffers = Vec::new();
    for (field, (name, dtype, shape, data)) in fields.into_iter().enumerate() {
        let data = if field < view_count {
            let shared = Arc::new(data);
            observation_buffers.push(shared.clone());
            prost::bytes::Bytes::from_owner(SharedBuffer(shared))
        } else {
            prost::bytes::Bytes::from(data)
        };
        let total = data.len();
        let mut offset = 0;
        loop {
            let end = (offset + chunk_bytes.max(1)).min(total);
            chunks.push(proto::BatchChunk {
                batch_index: batch.index,
                field: name.clone(),
                dtype: dtype as i32,
                shape: shape.clone(),
                offset: offset as u64,
                field_bytes: total as u64,
                last: false,
                data: data.slice(offset..end),
            });
            offset = end;
            if offset >= total {
                break;
            }
        }
    }
    if let Some(last) = chunks.last_mut() {
        last.last = true;
    }
    (chunks, observation_buffers)
}

/// A batch whose observations are in a shared-memory slot: descriptors of where they lie, and the
/// small fields inline. The slot is handed back to the caller, who holds it until the learner
/// releases the batch.
pub fn shared_batch_to_proto(mut batch: Batch, action: &Space) -> (proto::SharedBatch, Slot) {
    let slot = batch.slot.take().expect("a batch produced into shared memory carries its slot");
    let dtype = observation_dtype(&batch) as i32;
    let shared = batch
        .views
        .iter()
        .enumerate()
        .map(|(region, view)| {
            let tensor = proto::SharedTensor { dtype, shape: observation_shape(&batch, view), offset: slot.region_offset(region) as u64 };
            (view.name.clone(), tensor)
        })
        .collect();
    let tensors = small_fields(&mut batch, action)
        .into_iter()
        .map(|(name, dtype, shape, data)| (name, proto::Tensor { dtype: dtype as i32, shape, data: data.into() }))
        .collect();
    let message = proto::SharedBatch { batch_index: batch.index, slot: slot.index() as u32, shared, tensors };
    (message, slot)
}

pub fn tensor(dtype: DType, shape: Vec<usize>, data: Vec<u8>) -> proto::Tensor {
    proto::Tensor {
        dtype: dtype_to_proto(dtype) as i32,
        shape: shape.into_iter().map(|d| d as i64).collect(),
        data: data.into(),
    }
}

/// The batched observation tensor of a session: [rows, *observation shape].
pub fn observation_tensor(space: &Space, rows: usize, data: Vec<u8>) -> proto::Tensor {
    let mut shape = vec![rows];
    shape.extend_from_slice(space.shape());
    tensor(space.dtype(), shape, data)
}

/// Reads a request tensor's dtype and shape; the core checks them against the session's spec.
pub fn tensor_header(tensor: Option<&proto::Tensor>, what: &str) -> Result<(DType, Vec<usize>)> {
    let tensor = tensor.ok_or_else(|| ServiceError::BadRequest(format!("{what} tensor is missing")))?;
    let dtype = dtype_from_proto(tensor.dtype)?;
    let shape = tensor
        .shape
        .iter()
        .map(|&d| usize::try_from(d).map_err(|_| ServiceError::BadRequest(format!("{what} shape has a negative dimension {d}"))))
        .collect::<Result<Vec<_>>>()?;
    Ok((dtype, shape))
}

pub fn step_to_proto(space: &Space, outcome: StepOutcome) -> proto::StepResponse {
    let num_envs = outcome.rewards.len();
    let rewards: Vec<u8> = outcome.rewards.iter().flat_map(|r| r.to_le_bytes()).collect();
    proto::StepResponse {
        obs: Some(observation_tensor(space, num_envs, outcome.obs)),
        reward: Some(tensor(DType::Float64, vec![num_envs], rewards)),
        terminated: outcome.terminated,
        truncated: outcome.truncated,
        final_obs: Some(observation_tensor(space, outcome.episodes.len(), outcome.final_obs)),
        episodes: outcome.episodes.iter().map(episode_to_proto).collect(),
        step_infos: infos_to_proto(outcome.step_infos),
        reset_infos: infos_to_proto(outcome.reset_infos),
    }
}

/// A recv's outcome as its response: the ready envs' rows only, in env order.
pub fn recv_to_proto(space: &Space, ready: &[bool], mut outcome: StepOutcome) -> proto::RecvResponse {
    let env_ids: Vec<usize> = (0..ready.len()).filter(|&env| ready[env]).collect();
    let row = space.num_bytes();
    outcome.obs = env_ids.iter().flat_map(|&env| outcome.obs[env * row..][..row].iter().copied()).collect();
    outcome.rewards = env_ids.iter().map(|&env| outcome.rewards[env]).collect();
    outcome.terminated = env_ids.iter().map(|&env| outcome.terminated[env]).collect();
    outcome.truncated = env_ids.iter().map(|&env| outcome.truncated[env]).collect();
    proto::RecvResponse {
        env_ids: env_ids.iter().map(|&env| env as u32).collect(),
        step: Some(step_to_proto(space, outcome)),
    }
}

/// Info columns as the API sends them (`InfoColumn`): a numeric column's values as a tensor
/// [envs, *shape], a text or JSON column's as texts.
pub fn infos_to_proto(infos: Infos) -> Vec<proto::InfoColumn> {
    infos
        .columns
        .into_iter()
        .map(|column| {
            let kind = match column.kind {
                InfoKind::Python => proto::InfoKind::Python,
                InfoKind::Scalar => proto::InfoKind::Scalar,
                InfoKind::Array => proto::InfoKind::Array,
                InfoKind::Text => proto::InfoKind::Text,
                InfoKind::Json => proto::InfoKind::Json,
            };
            let values = column.kind.numeric().then(|| {
                let shape = std::iter::once(column.envs.len()).chain(column.shape.iter().map(|&d| d as usize)).collect();
                tensor(column.dtype, shape, column.data)
            });
            proto::InfoColumn { path: column.path, envs: column.envs, kind: kind as i32, values, texts: column.texts }
        })
        .collect()
}

fn episode_to_proto(episode: &EpisodeEnd) -> proto::EpisodeEnd {
    proto::EpisodeEnd {
        env_index: episode.env_index as u32,
        episode_return: episode.episode_return,
        episode_length: episode.episode_length,
        terminated: episode.terminated,
        truncated: episode.truncated,
        error: episode.error.clone().unwrap_or_default(),
    }
}
