from google.protobuf.internal import containers as _containers
from google.protobuf.internal import enum_type_wrapper as _enum_type_wrapper
from google.protobuf import descriptor as _descriptor
from google.protobuf import message as _message
from collections.abc import Iterable as _Iterable, Mapping as _Mapping
from typing import ClassVar as _ClassVar, Optional as _Optional, Union as _Union

DESCRIPTOR: _descriptor.FileDescriptor

class DType(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    DTYPE_UNSPECIFIED: _ClassVar[DType]
    DTYPE_UINT8: _ClassVar[DType]
    DTYPE_INT32: _ClassVar[DType]
    DTYPE_INT64: _ClassVar[DType]
    DTYPE_FLOAT32: _ClassVar[DType]
    DTYPE_FLOAT64: _ClassVar[DType]
    DTYPE_BOOL: _ClassVar[DType]

class PolicyHead(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    POLICY_HEAD_UNSPECIFIED: _ClassVar[PolicyHead]
    POLICY_HEAD_GAUSSIAN_TANH: _ClassVar[PolicyHead]
    POLICY_HEAD_CATEGORICAL: _ClassVar[PolicyHead]
    POLICY_HEAD_DETERMINISTIC_NOISE: _ClassVar[PolicyHead]

class InfoKind(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    INFO_KIND_UNSPECIFIED: _ClassVar[InfoKind]
    INFO_KIND_PYTHON: _ClassVar[InfoKind]
    INFO_KIND_SCALAR: _ClassVar[InfoKind]
    INFO_KIND_ARRAY: _ClassVar[InfoKind]
    INFO_KIND_TEXT: _ClassVar[InfoKind]
    INFO_KIND_JSON: _ClassVar[InfoKind]

class DrawSharing(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    DRAW_SHARING_REFERENCE: _ClassVar[DrawSharing]
    DRAW_SHARING_SHARED: _ClassVar[DrawSharing]
    DRAW_SHARING_INDEPENDENT: _ClassVar[DrawSharing]

class ViewOf(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    VIEW_OF_UNSPECIFIED: _ClassVar[ViewOf]
    VIEW_OF_OBS: _ClassVar[ViewOf]
    VIEW_OF_NEXT_OBS: _ClassVar[ViewOf]

class SequenceBoundary(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    SEQUENCE_BOUNDARY_WITHIN_EPISODE: _ClassVar[SequenceBoundary]
    SEQUENCE_BOUNDARY_ACROSS_EPISODES: _ClassVar[SequenceBoundary]

class Sampler(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    SAMPLER_UNIFORM: _ClassVar[Sampler]
    SAMPLER_PRIORITIZED: _ClassVar[Sampler]

class BatchSource(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    SOURCE_REPLAY: _ClassVar[BatchSource]
    SOURCE_ROLLOUT: _ClassVar[BatchSource]
DTYPE_UNSPECIFIED: DType
DTYPE_UINT8: DType
DTYPE_INT32: DType
DTYPE_INT64: DType
DTYPE_FLOAT32: DType
DTYPE_FLOAT64: DType
DTYPE_BOOL: DType
POLICY_HEAD_UNSPECIFIED: PolicyHead
POLICY_HEAD_GAUSSIAN_TANH: PolicyHead
POLICY_HEAD_CATEGORICAL: PolicyHead
POLICY_HEAD_DETERMINISTIC_NOISE: PolicyHead
INFO_KIND_UNSPECIFIED: InfoKind
INFO_KIND_PYTHON: InfoKind
INFO_KIND_SCALAR: InfoKind
INFO_KIND_ARRAY: InfoKind
INFO_KIND_TEXT: InfoKind
INFO_KIND_JSON: InfoKind
DRAW_SHARING_REFERENCE: DrawSharing
DRAW_SHARING_SHARED: DrawSharing
DRAW_SHARING_INDEPENDENT: DrawSharing
VIEW_OF_UNSPECIFIED: ViewOf
VIEW_OF_OBS: ViewOf
VIEW_OF_NEXT_OBS: ViewOf
SEQUENCE_BOUNDARY_WITHIN_EPISODE: SequenceBoundary
SEQUENCE_BOUNDARY_ACROSS_EPISODES: SequenceBoundary
SAMPLER_UNIFORM: Sampler
SAMPLER_PRIORITIZED: Sampler
SOURCE_REPLAY: BatchSource
SOURCE_ROLLOUT: BatchSource

class Tensor(_message.Message):
    __slots__ = ("dtype", "shape", "data")
    DTYPE_FIELD_NUMBER: _ClassVar[int]
    SHAPE_FIELD_NUMBER: _ClassVar[int]
    DATA_FIELD_NUMBER: _ClassVar[int]
    dtype: DType
    shape: _containers.RepeatedScalarFieldContainer[int]
    data: bytes
    def __init__(self, dtype: _Optional[_Union[DType, str]] = ..., shape: _Optional[_Iterable[int]] = ..., data: _Optional[bytes] = ...) -> None: ...

class BoxSpace(_message.Message):
    __slots__ = ("dtype", "shape", "low", "high")
    DTYPE_FIELD_NUMBER: _ClassVar[int]
    SHAPE_FIELD_NUMBER: _ClassVar[int]
    LOW_FIELD_NUMBER: _ClassVar[int]
    HIGH_FIELD_NUMBER: _ClassVar[int]
    dtype: DType
    shape: _containers.RepeatedScalarFieldContainer[int]
    low: _containers.RepeatedScalarFieldContainer[float]
    high: _containers.RepeatedScalarFieldContainer[float]
    def __init__(self, dtype: _Optional[_Union[DType, str]] = ..., shape: _Optional[_Iterable[int]] = ..., low: _Optional[_Iterable[float]] = ..., high: _Optional[_Iterable[float]] = ...) -> None: ...

class DiscreteSpace(_message.Message):
    __slots__ = ("n",)
    N_FIELD_NUMBER: _ClassVar[int]
    n: int
    def __init__(self, n: _Optional[int] = ...) -> None: ...

class Space(_message.Message):
    __slots__ = ("box", "discrete")
    BOX_FIELD_NUMBER: _ClassVar[int]
    DISCRETE_FIELD_NUMBER: _ClassVar[int]
    box: BoxSpace
    discrete: DiscreteSpace
    def __init__(self, box: _Optional[_Union[BoxSpace, _Mapping]] = ..., discrete: _Optional[_Union[DiscreteSpace, _Mapping]] = ...) -> None: ...

class OptionValue(_message.Message):
    __slots__ = ("bool_value", "int_value", "float_value", "string_value")
    BOOL_VALUE_FIELD_NUMBER: _ClassVar[int]
    INT_VALUE_FIELD_NUMBER: _ClassVar[int]
    FLOAT_VALUE_FIELD_NUMBER: _ClassVar[int]
    STRING_VALUE_FIELD_NUMBER: _ClassVar[int]
    bool_value: bool
    int_value: int
    float_value: float
    string_value: str
    def __init__(self, bool_value: _Optional[bool] = ..., int_value: _Optional[int] = ..., float_value: _Optional[float] = ..., string_value: _Optional[str] = ...) -> None: ...

class EnvInfo(_message.Message):
    __slots__ = ("id", "family", "observation_space", "action_space", "default_options")
    class DefaultOptionsEntry(_message.Message):
        __slots__ = ("key", "value")
        KEY_FIELD_NUMBER: _ClassVar[int]
        VALUE_FIELD_NUMBER: _ClassVar[int]
        key: str
        value: OptionValue
        def __init__(self, key: _Optional[str] = ..., value: _Optional[_Union[OptionValue, _Mapping]] = ...) -> None: ...
    ID_FIELD_NUMBER: _ClassVar[int]
    FAMILY_FIELD_NUMBER: _ClassVar[int]
    OBSERVATION_SPACE_FIELD_NUMBER: _ClassVar[int]
    ACTION_SPACE_FIELD_NUMBER: _ClassVar[int]
    DEFAULT_OPTIONS_FIELD_NUMBER: _ClassVar[int]
    id: str
    family: str
    observation_space: Space
    action_space: Space
    default_options: _containers.MessageMap[str, OptionValue]
    def __init__(self, id: _Optional[str] = ..., family: _Optional[str] = ..., observation_space: _Optional[_Union[Space, _Mapping]] = ..., action_space: _Optional[_Union[Space, _Mapping]] = ..., default_options: _Optional[_Mapping[str, OptionValue]] = ...) -> None: ...

class ServerInfoRequest(_message.Message):
    __slots__ = ()
    def __init__(self) -> None: ...

class ServerInfoResponse(_message.Message):
    __slots__ = ("version", "api")
    VERSION_FIELD_NUMBER: _ClassVar[int]
    API_FIELD_NUMBER: _ClassVar[int]
    version: str
    api: str
    def __init__(self, version: _Optional[str] = ..., api: _Optional[str] = ...) -> None: ...

class ListEnvsRequest(_message.Message):
    __slots__ = ("prefix",)
    PREFIX_FIELD_NUMBER: _ClassVar[int]
    prefix: str
    def __init__(self, prefix: _Optional[str] = ...) -> None: ...

class ListEnvsResponse(_message.Message):
    __slots__ = ("envs",)
    ENVS_FIELD_NUMBER: _ClassVar[int]
    envs: _containers.RepeatedCompositeFieldContainer[EnvInfo]
    def __init__(self, envs: _Optional[_Iterable[_Union[EnvInfo, _Mapping]]] = ...) -> None: ...

class CreateSessionRequest(_message.Message):
    __slots__ = ("env_id", "num_envs", "seed", "options", "replay", "observation_view", "name")
    class OptionsEntry(_message.Message):
        __slots__ = ("key", "value")
        KEY_FIELD_NUMBER: _ClassVar[int]
        VALUE_FIELD_NUMBER: _ClassVar[int]
        key: str
        value: OptionValue
        def __init__(self, key: _Optional[str] = ..., value: _Optional[_Union[OptionValue, _Mapping]] = ...) -> None: ...
    ENV_ID_FIELD_NUMBER: _ClassVar[int]
    NUM_ENVS_FIELD_NUMBER: _ClassVar[int]
    SEED_FIELD_NUMBER: _ClassVar[int]
    OPTIONS_FIELD_NUMBER: _ClassVar[int]
    REPLAY_FIELD_NUMBER: _ClassVar[int]
    OBSERVATION_VIEW_FIELD_NUMBER: _ClassVar[int]
    NAME_FIELD_NUMBER: _ClassVar[int]
    env_id: str
    num_envs: int
    seed: int
    options: _containers.MessageMap[str, OptionValue]
    replay: ReplayOptions
    observation_view: str
    name: str
    def __init__(self, env_id: _Optional[str] = ..., num_envs: _Optional[int] = ..., seed: _Optional[int] = ..., options: _Optional[_Mapping[str, OptionValue]] = ..., replay: _Optional[_Union[ReplayOptions, _Mapping]] = ..., observation_view: _Optional[str] = ..., name: _Optional[str] = ...) -> None: ...

class ReplayOptions(_message.Message):
    __slots__ = ("capacity", "rollout_steps")
    CAPACITY_FIELD_NUMBER: _ClassVar[int]
    ROLLOUT_STEPS_FIELD_NUMBER: _ClassVar[int]
    capacity: int
    rollout_steps: int
    def __init__(self, capacity: _Optional[int] = ..., rollout_steps: _Optional[int] = ...) -> None: ...

class ReplayInfo(_message.Message):
    __slots__ = ("capacity", "size", "inserts", "samples", "memory_bytes", "frames_per_transition", "active_streams", "rollout_steps", "batches", "batches_per_second", "snapshot")
    CAPACITY_FIELD_NUMBER: _ClassVar[int]
    SIZE_FIELD_NUMBER: _ClassVar[int]
    INSERTS_FIELD_NUMBER: _ClassVar[int]
    SAMPLES_FIELD_NUMBER: _ClassVar[int]
    MEMORY_BYTES_FIELD_NUMBER: _ClassVar[int]
    FRAMES_PER_TRANSITION_FIELD_NUMBER: _ClassVar[int]
    ACTIVE_STREAMS_FIELD_NUMBER: _ClassVar[int]
    ROLLOUT_STEPS_FIELD_NUMBER: _ClassVar[int]
    BATCHES_FIELD_NUMBER: _ClassVar[int]
    BATCHES_PER_SECOND_FIELD_NUMBER: _ClassVar[int]
    SNAPSHOT_FIELD_NUMBER: _ClassVar[int]
    capacity: int
    size: int
    inserts: int
    samples: int
    memory_bytes: int
    frames_per_transition: float
    active_streams: int
    rollout_steps: int
    batches: int
    batches_per_second: float
    snapshot: ReplaySnapshot
    def __init__(self, capacity: _Optional[int] = ..., size: _Optional[int] = ..., inserts: _Optional[int] = ..., samples: _Optional[int] = ..., memory_bytes: _Optional[int] = ..., frames_per_transition: _Optional[float] = ..., active_streams: _Optional[int] = ..., rollout_steps: _Optional[int] = ..., batches: _Optional[int] = ..., batches_per_second: _Optional[float] = ..., snapshot: _Optional[_Union[ReplaySnapshot, _Mapping]] = ...) -> None: ...

class ReplaySnapshot(_message.Message):
    __slots__ = ("restored_transitions", "disk_bytes", "age_seconds", "pending_frames")
    RESTORED_TRANSITIONS_FIELD_NUMBER: _ClassVar[int]
    DISK_BYTES_FIELD_NUMBER: _ClassVar[int]
    AGE_SECONDS_FIELD_NUMBER: _ClassVar[int]
    PENDING_FRAMES_FIELD_NUMBER: _ClassVar[int]
    restored_transitions: int
    disk_bytes: int
    age_seconds: float
    pending_frames: int
    def __init__(self, restored_transitions: _Optional[int] = ..., disk_bytes: _Optional[int] = ..., age_seconds: _Optional[float] = ..., pending_frames: _Optional[int] = ...) -> None: ...

class SessionInfo(_message.Message):
    __slots__ = ("session_id", "env_id", "num_envs", "seed", "options", "observation_space", "action_space", "frame_stack", "autoreset_mode", "total_env_steps", "episodes_completed", "replay", "name", "acting")
    class OptionsEntry(_message.Message):
        __slots__ = ("key", "value")
        KEY_FIELD_NUMBER: _ClassVar[int]
        VALUE_FIELD_NUMBER: _ClassVar[int]
        key: str
        value: OptionValue
        def __init__(self, key: _Optional[str] = ..., value: _Optional[_Union[OptionValue, _Mapping]] = ...) -> None: ...
    SESSION_ID_FIELD_NUMBER: _ClassVar[int]
    ENV_ID_FIELD_NUMBER: _ClassVar[int]
    NUM_ENVS_FIELD_NUMBER: _ClassVar[int]
    SEED_FIELD_NUMBER: _ClassVar[int]
    OPTIONS_FIELD_NUMBER: _ClassVar[int]
    OBSERVATION_SPACE_FIELD_NUMBER: _ClassVar[int]
    ACTION_SPACE_FIELD_NUMBER: _ClassVar[int]
    FRAME_STACK_FIELD_NUMBER: _ClassVar[int]
    AUTORESET_MODE_FIELD_NUMBER: _ClassVar[int]
    TOTAL_ENV_STEPS_FIELD_NUMBER: _ClassVar[int]
    EPISODES_COMPLETED_FIELD_NUMBER: _ClassVar[int]
    REPLAY_FIELD_NUMBER: _ClassVar[int]
    NAME_FIELD_NUMBER: _ClassVar[int]
    ACTING_FIELD_NUMBER: _ClassVar[int]
    session_id: str
    env_id: str
    num_envs: int
    seed: int
    options: _containers.MessageMap[str, OptionValue]
    observation_space: Space
    action_space: Space
    frame_stack: int
    autoreset_mode: str
    total_env_steps: int
    episodes_completed: int
    replay: ReplayInfo
    name: str
    acting: ActingInfo
    def __init__(self, session_id: _Optional[str] = ..., env_id: _Optional[str] = ..., num_envs: _Optional[int] = ..., seed: _Optional[int] = ..., options: _Optional[_Mapping[str, OptionValue]] = ..., observation_space: _Optional[_Union[Space, _Mapping]] = ..., action_space: _Optional[_Union[Space, _Mapping]] = ..., frame_stack: _Optional[int] = ..., autoreset_mode: _Optional[str] = ..., total_env_steps: _Optional[int] = ..., episodes_completed: _Optional[int] = ..., replay: _Optional[_Union[ReplayInfo, _Mapping]] = ..., name: _Optional[str] = ..., acting: _Optional[_Union[ActingInfo, _Mapping]] = ...) -> None: ...

class NoiseSchedule(_message.Message):
    __slots__ = ("std_start", "std_end", "std_steps", "clip")
    STD_START_FIELD_NUMBER: _ClassVar[int]
    STD_END_FIELD_NUMBER: _ClassVar[int]
    STD_STEPS_FIELD_NUMBER: _ClassVar[int]
    CLIP_FIELD_NUMBER: _ClassVar[int]
    std_start: float
    std_end: float
    std_steps: int
    clip: float
    def __init__(self, std_start: _Optional[float] = ..., std_end: _Optional[float] = ..., std_steps: _Optional[int] = ..., clip: _Optional[float] = ...) -> None: ...

class SetPolicyRequest(_message.Message):
    __slots__ = ("session_id", "model", "head", "version", "noise")
    SESSION_ID_FIELD_NUMBER: _ClassVar[int]
    MODEL_FIELD_NUMBER: _ClassVar[int]
    HEAD_FIELD_NUMBER: _ClassVar[int]
    VERSION_FIELD_NUMBER: _ClassVar[int]
    NOISE_FIELD_NUMBER: _ClassVar[int]
    session_id: str
    model: bytes
    head: PolicyHead
    version: int
    noise: NoiseSchedule
    def __init__(self, session_id: _Optional[str] = ..., model: _Optional[bytes] = ..., head: _Optional[_Union[PolicyHead, str]] = ..., version: _Optional[int] = ..., noise: _Optional[_Union[NoiseSchedule, _Mapping]] = ...) -> None: ...

class SetPolicyResponse(_message.Message):
    __slots__ = ("version", "ops", "opset", "input", "outputs", "has_value")
    VERSION_FIELD_NUMBER: _ClassVar[int]
    OPS_FIELD_NUMBER: _ClassVar[int]
    OPSET_FIELD_NUMBER: _ClassVar[int]
    INPUT_FIELD_NUMBER: _ClassVar[int]
    OUTPUTS_FIELD_NUMBER: _ClassVar[int]
    HAS_VALUE_FIELD_NUMBER: _ClassVar[int]
    version: int
    ops: _containers.RepeatedScalarFieldContainer[str]
    opset: int
    input: str
    outputs: _containers.RepeatedScalarFieldContainer[str]
    has_value: bool
    def __init__(self, version: _Optional[int] = ..., ops: _Optional[_Iterable[str]] = ..., opset: _Optional[int] = ..., input: _Optional[str] = ..., outputs: _Optional[_Iterable[str]] = ..., has_value: _Optional[bool] = ...) -> None: ...

class StartActingRequest(_message.Message):
    __slots__ = ("session_id", "steps_per_second", "random_steps", "eval", "samples_per_insert", "error_buffer", "min_size", "seed", "max_episodes", "max_env_steps")
    SESSION_ID_FIELD_NUMBER: _ClassVar[int]
    STEPS_PER_SECOND_FIELD_NUMBER: _ClassVar[int]
    RANDOM_STEPS_FIELD_NUMBER: _ClassVar[int]
    EVAL_FIELD_NUMBER: _ClassVar[int]
    SAMPLES_PER_INSERT_FIELD_NUMBER: _ClassVar[int]
    ERROR_BUFFER_FIELD_NUMBER: _ClassVar[int]
    MIN_SIZE_FIELD_NUMBER: _ClassVar[int]
    SEED_FIELD_NUMBER: _ClassVar[int]
    MAX_EPISODES_FIELD_NUMBER: _ClassVar[int]
    MAX_ENV_STEPS_FIELD_NUMBER: _ClassVar[int]
    session_id: str
    steps_per_second: float
    random_steps: int
    eval: bool
    samples_per_insert: float
    error_buffer: float
    min_size: int
    seed: int
    max_episodes: int
    max_env_steps: int
    def __init__(self, session_id: _Optional[str] = ..., steps_per_second: _Optional[float] = ..., random_steps: _Optional[int] = ..., eval: _Optional[bool] = ..., samples_per_insert: _Optional[float] = ..., error_buffer: _Optional[float] = ..., min_size: _Optional[int] = ..., seed: _Optional[int] = ..., max_episodes: _Optional[int] = ..., max_env_steps: _Optional[int] = ...) -> None: ...

class StopActingRequest(_message.Message):
    __slots__ = ("session_id",)
    SESSION_ID_FIELD_NUMBER: _ClassVar[int]
    session_id: str
    def __init__(self, session_id: _Optional[str] = ...) -> None: ...

class ActingInfo(_message.Message):
    __slots__ = ("state", "policy_version", "acting_version", "head", "env_steps", "episodes", "recent_returns", "inference_seconds", "step_seconds", "limited_seconds", "error", "recent_envs")
    STATE_FIELD_NUMBER: _ClassVar[int]
    POLICY_VERSION_FIELD_NUMBER: _ClassVar[int]
    ACTING_VERSION_FIELD_NUMBER: _ClassVar[int]
    HEAD_FIELD_NUMBER: _ClassVar[int]
    ENV_STEPS_FIELD_NUMBER: _ClassVar[int]
    EPISODES_FIELD_NUMBER: _ClassVar[int]
    RECENT_RETURNS_FIELD_NUMBER: _ClassVar[int]
    INFERENCE_SECONDS_FIELD_NUMBER: _ClassVar[int]
    STEP_SECONDS_FIELD_NUMBER: _ClassVar[int]
    LIMITED_SECONDS_FIELD_NUMBER: _ClassVar[int]
    ERROR_FIELD_NUMBER: _ClassVar[int]
    RECENT_ENVS_FIELD_NUMBER: _ClassVar[int]
    state: str
    policy_version: int
    acting_version: int
    head: str
    env_steps: int
    episodes: int
    recent_returns: _containers.RepeatedScalarFieldContainer[float]
    inference_seconds: float
    step_seconds: float
    limited_seconds: float
    error: str
    recent_envs: _containers.RepeatedScalarFieldContainer[int]
    def __init__(self, state: _Optional[str] = ..., policy_version: _Optional[int] = ..., acting_version: _Optional[int] = ..., head: _Optional[str] = ..., env_steps: _Optional[int] = ..., episodes: _Optional[int] = ..., recent_returns: _Optional[_Iterable[float]] = ..., inference_seconds: _Optional[float] = ..., step_seconds: _Optional[float] = ..., limited_seconds: _Optional[float] = ..., error: _Optional[str] = ..., recent_envs: _Optional[_Iterable[int]] = ...) -> None: ...

class DescribeSessionRequest(_message.Message):
    __slots__ = ("session_id",)
    SESSION_ID_FIELD_NUMBER: _ClassVar[int]
    session_id: str
    def __init__(self, session_id: _Optional[str] = ...) -> None: ...

class CloseSessionRequest(_message.Message):
    __slots__ = ("session_id", "discard_snapshot")
    SESSION_ID_FIELD_NUMBER: _ClassVar[int]
    DISCARD_SNAPSHOT_FIELD_NUMBER: _ClassVar[int]
    session_id: str
    discard_snapshot: bool
    def __init__(self, session_id: _Optional[str] = ..., discard_snapshot: _Optional[bool] = ...) -> None: ...

class CloseSessionResponse(_message.Message):
    __slots__ = ()
    def __init__(self) -> None: ...

class ListSessionsRequest(_message.Message):
    __slots__ = ()
    def __init__(self) -> None: ...

class SessionSummary(_message.Message):
    __slots__ = ("session_id", "env_id", "num_envs", "memory_bytes", "idle_seconds", "open_streams", "age_seconds", "owner", "name")
    SESSION_ID_FIELD_NUMBER: _ClassVar[int]
    ENV_ID_FIELD_NUMBER: _ClassVar[int]
    NUM_ENVS_FIELD_NUMBER: _ClassVar[int]
    MEMORY_BYTES_FIELD_NUMBER: _ClassVar[int]
    IDLE_SECONDS_FIELD_NUMBER: _ClassVar[int]
    OPEN_STREAMS_FIELD_NUMBER: _ClassVar[int]
    AGE_SECONDS_FIELD_NUMBER: _ClassVar[int]
    OWNER_FIELD_NUMBER: _ClassVar[int]
    NAME_FIELD_NUMBER: _ClassVar[int]
    session_id: str
    env_id: str
    num_envs: int
    memory_bytes: int
    idle_seconds: float
    open_streams: int
    age_seconds: float
    owner: str
    name: str
    def __init__(self, session_id: _Optional[str] = ..., env_id: _Optional[str] = ..., num_envs: _Optional[int] = ..., memory_bytes: _Optional[int] = ..., idle_seconds: _Optional[float] = ..., open_streams: _Optional[int] = ..., age_seconds: _Optional[float] = ..., owner: _Optional[str] = ..., name: _Optional[str] = ...) -> None: ...

class ListSessionsResponse(_message.Message):
    __slots__ = ("sessions", "idle_timeout_seconds")
    SESSIONS_FIELD_NUMBER: _ClassVar[int]
    IDLE_TIMEOUT_SECONDS_FIELD_NUMBER: _ClassVar[int]
    sessions: _containers.RepeatedCompositeFieldContainer[SessionSummary]
    idle_timeout_seconds: float
    def __init__(self, sessions: _Optional[_Iterable[_Union[SessionSummary, _Mapping]]] = ..., idle_timeout_seconds: _Optional[float] = ...) -> None: ...

class ResetRequest(_message.Message):
    __slots__ = ("session_id", "seed", "mask", "env_seeds")
    SESSION_ID_FIELD_NUMBER: _ClassVar[int]
    SEED_FIELD_NUMBER: _ClassVar[int]
    MASK_FIELD_NUMBER: _ClassVar[int]
    ENV_SEEDS_FIELD_NUMBER: _ClassVar[int]
    session_id: str
    seed: int
    mask: _containers.RepeatedScalarFieldContainer[bool]
    env_seeds: _containers.RepeatedScalarFieldContainer[int]
    def __init__(self, session_id: _Optional[str] = ..., seed: _Optional[int] = ..., mask: _Optional[_Iterable[bool]] = ..., env_seeds: _Optional[_Iterable[int]] = ...) -> None: ...

class ResetResponse(_message.Message):
    __slots__ = ("obs", "reset_infos")
    OBS_FIELD_NUMBER: _ClassVar[int]
    RESET_INFOS_FIELD_NUMBER: _ClassVar[int]
    obs: Tensor
    reset_infos: _containers.RepeatedCompositeFieldContainer[InfoColumn]
    def __init__(self, obs: _Optional[_Union[Tensor, _Mapping]] = ..., reset_infos: _Optional[_Iterable[_Union[InfoColumn, _Mapping]]] = ...) -> None: ...

class InfoColumn(_message.Message):
    __slots__ = ("path", "envs", "kind", "values", "texts")
    PATH_FIELD_NUMBER: _ClassVar[int]
    ENVS_FIELD_NUMBER: _ClassVar[int]
    KIND_FIELD_NUMBER: _ClassVar[int]
    VALUES_FIELD_NUMBER: _ClassVar[int]
    TEXTS_FIELD_NUMBER: _ClassVar[int]
    path: _containers.RepeatedScalarFieldContainer[str]
    envs: _containers.RepeatedScalarFieldContainer[int]
    kind: InfoKind
    values: Tensor
    texts: _containers.RepeatedScalarFieldContainer[str]
    def __init__(self, path: _Optional[_Iterable[str]] = ..., envs: _Optional[_Iterable[int]] = ..., kind: _Optional[_Union[InfoKind, str]] = ..., values: _Optional[_Union[Tensor, _Mapping]] = ..., texts: _Optional[_Iterable[str]] = ...) -> None: ...

class InfoColumns(_message.Message):
    __slots__ = ("columns",)
    COLUMNS_FIELD_NUMBER: _ClassVar[int]
    columns: _containers.RepeatedCompositeFieldContainer[InfoColumn]
    def __init__(self, columns: _Optional[_Iterable[_Union[InfoColumn, _Mapping]]] = ...) -> None: ...

class StepRequest(_message.Message):
    __slots__ = ("session_id", "actions", "skip")
    SESSION_ID_FIELD_NUMBER: _ClassVar[int]
    ACTIONS_FIELD_NUMBER: _ClassVar[int]
    SKIP_FIELD_NUMBER: _ClassVar[int]
    session_id: str
    actions: Tensor
    skip: _containers.RepeatedScalarFieldContainer[bool]
    def __init__(self, session_id: _Optional[str] = ..., actions: _Optional[_Union[Tensor, _Mapping]] = ..., skip: _Optional[_Iterable[bool]] = ...) -> None: ...

class EpisodeEnd(_message.Message):
    __slots__ = ("env_index", "episode_return", "episode_length", "terminated", "truncated", "error")
    ENV_INDEX_FIELD_NUMBER: _ClassVar[int]
    EPISODE_RETURN_FIELD_NUMBER: _ClassVar[int]
    EPISODE_LENGTH_FIELD_NUMBER: _ClassVar[int]
    TERMINATED_FIELD_NUMBER: _ClassVar[int]
    TRUNCATED_FIELD_NUMBER: _ClassVar[int]
    ERROR_FIELD_NUMBER: _ClassVar[int]
    env_index: int
    episode_return: float
    episode_length: int
    terminated: bool
    truncated: bool
    error: str
    def __init__(self, env_index: _Optional[int] = ..., episode_return: _Optional[float] = ..., episode_length: _Optional[int] = ..., terminated: _Optional[bool] = ..., truncated: _Optional[bool] = ..., error: _Optional[str] = ...) -> None: ...

class StepResponse(_message.Message):
    __slots__ = ("obs", "reward", "terminated", "truncated", "episodes", "final_obs", "step_infos", "reset_infos")
    OBS_FIELD_NUMBER: _ClassVar[int]
    REWARD_FIELD_NUMBER: _ClassVar[int]
    TERMINATED_FIELD_NUMBER: _ClassVar[int]
    TRUNCATED_FIELD_NUMBER: _ClassVar[int]
    EPISODES_FIELD_NUMBER: _ClassVar[int]
    FINAL_OBS_FIELD_NUMBER: _ClassVar[int]
    STEP_INFOS_FIELD_NUMBER: _ClassVar[int]
    RESET_INFOS_FIELD_NUMBER: _ClassVar[int]
    obs: Tensor
    reward: Tensor
    terminated: _containers.RepeatedScalarFieldContainer[bool]
    truncated: _containers.RepeatedScalarFieldContainer[bool]
    episodes: _containers.RepeatedCompositeFieldContainer[EpisodeEnd]
    final_obs: Tensor
    step_infos: _containers.RepeatedCompositeFieldContainer[InfoColumn]
    reset_infos: _containers.RepeatedCompositeFieldContainer[InfoColumn]
    def __init__(self, obs: _Optional[_Union[Tensor, _Mapping]] = ..., reward: _Optional[_Union[Tensor, _Mapping]] = ..., terminated: _Optional[_Iterable[bool]] = ..., truncated: _Optional[_Iterable[bool]] = ..., episodes: _Optional[_Iterable[_Union[EpisodeEnd, _Mapping]]] = ..., final_obs: _Optional[_Union[Tensor, _Mapping]] = ..., step_infos: _Optional[_Iterable[_Union[InfoColumn, _Mapping]]] = ..., reset_infos: _Optional[_Iterable[_Union[InfoColumn, _Mapping]]] = ...) -> None: ...

class AsyncResetRequest(_message.Message):
    __slots__ = ("session_id", "seed")
    SESSION_ID_FIELD_NUMBER: _ClassVar[int]
    SEED_FIELD_NUMBER: _ClassVar[int]
    session_id: str
    seed: int
    def __init__(self, session_id: _Optional[str] = ..., seed: _Optional[int] = ...) -> None: ...

class AsyncResetResponse(_message.Message):
    __slots__ = ()
    def __init__(self) -> None: ...

class SendRequest(_message.Message):
    __slots__ = ("session_id", "actions", "env_ids")
    SESSION_ID_FIELD_NUMBER: _ClassVar[int]
    ACTIONS_FIELD_NUMBER: _ClassVar[int]
    ENV_IDS_FIELD_NUMBER: _ClassVar[int]
    session_id: str
    actions: Tensor
    env_ids: _containers.RepeatedScalarFieldContainer[int]
    def __init__(self, session_id: _Optional[str] = ..., actions: _Optional[_Union[Tensor, _Mapping]] = ..., env_ids: _Optional[_Iterable[int]] = ...) -> None: ...

class SendResponse(_message.Message):
    __slots__ = ()
    def __init__(self) -> None: ...

class RecvRequest(_message.Message):
    __slots__ = ("session_id", "actions", "env_ids")
    SESSION_ID_FIELD_NUMBER: _ClassVar[int]
    ACTIONS_FIELD_NUMBER: _ClassVar[int]
    ENV_IDS_FIELD_NUMBER: _ClassVar[int]
    session_id: str
    actions: Tensor
    env_ids: _containers.RepeatedScalarFieldContainer[int]
    def __init__(self, session_id: _Optional[str] = ..., actions: _Optional[_Union[Tensor, _Mapping]] = ..., env_ids: _Optional[_Iterable[int]] = ...) -> None: ...

class RecvResponse(_message.Message):
    __slots__ = ("env_ids", "step")
    ENV_IDS_FIELD_NUMBER: _ClassVar[int]
    STEP_FIELD_NUMBER: _ClassVar[int]
    env_ids: _containers.RepeatedScalarFieldContainer[int]
    step: StepResponse
    def __init__(self, env_ids: _Optional[_Iterable[int]] = ..., step: _Optional[_Union[StepResponse, _Mapping]] = ...) -> None: ...

class ActRequest(_message.Message):
    __slots__ = ("reset", "step")
    RESET_FIELD_NUMBER: _ClassVar[int]
    STEP_FIELD_NUMBER: _ClassVar[int]
    reset: ResetRequest
    step: StepRequest
    def __init__(self, reset: _Optional[_Union[ResetRequest, _Mapping]] = ..., step: _Optional[_Union[StepRequest, _Mapping]] = ...) -> None: ...

class ActResponse(_message.Message):
    __slots__ = ("reset", "step")
    RESET_FIELD_NUMBER: _ClassVar[int]
    STEP_FIELD_NUMBER: _ClassVar[int]
    reset: ResetResponse
    step: StepResponse
    def __init__(self, reset: _Optional[_Union[ResetResponse, _Mapping]] = ..., step: _Optional[_Union[StepResponse, _Mapping]] = ...) -> None: ...

class ShareActingRequest(_message.Message):
    __slots__ = ("session_id",)
    SESSION_ID_FIELD_NUMBER: _ClassVar[int]
    session_id: str
    def __init__(self, session_id: _Optional[str] = ...) -> None: ...

class SharedActingChannel(_message.Message):
    __slots__ = ("size", "token", "socket", "actions_offset", "obs_offset", "final_obs_offset", "reward_offset", "terminated_offset", "truncated_offset", "episode_return_offset", "episode_length_offset", "mask_offset", "env_seeds_offset")
    SIZE_FIELD_NUMBER: _ClassVar[int]
    TOKEN_FIELD_NUMBER: _ClassVar[int]
    SOCKET_FIELD_NUMBER: _ClassVar[int]
    ACTIONS_OFFSET_FIELD_NUMBER: _ClassVar[int]
    OBS_OFFSET_FIELD_NUMBER: _ClassVar[int]
    FINAL_OBS_OFFSET_FIELD_NUMBER: _ClassVar[int]
    REWARD_OFFSET_FIELD_NUMBER: _ClassVar[int]
    TERMINATED_OFFSET_FIELD_NUMBER: _ClassVar[int]
    TRUNCATED_OFFSET_FIELD_NUMBER: _ClassVar[int]
    EPISODE_RETURN_OFFSET_FIELD_NUMBER: _ClassVar[int]
    EPISODE_LENGTH_OFFSET_FIELD_NUMBER: _ClassVar[int]
    MASK_OFFSET_FIELD_NUMBER: _ClassVar[int]
    ENV_SEEDS_OFFSET_FIELD_NUMBER: _ClassVar[int]
    size: int
    token: bytes
    socket: str
    actions_offset: int
    obs_offset: int
    final_obs_offset: int
    reward_offset: int
    terminated_offset: int
    truncated_offset: int
    episode_return_offset: int
    episode_length_offset: int
    mask_offset: int
    env_seeds_offset: int
    def __init__(self, size: _Optional[int] = ..., token: _Optional[bytes] = ..., socket: _Optional[str] = ..., actions_offset: _Optional[int] = ..., obs_offset: _Optional[int] = ..., final_obs_offset: _Optional[int] = ..., reward_offset: _Optional[int] = ..., terminated_offset: _Optional[int] = ..., truncated_offset: _Optional[int] = ..., episode_return_offset: _Optional[int] = ..., episode_length_offset: _Optional[int] = ..., mask_offset: _Optional[int] = ..., env_seeds_offset: _Optional[int] = ...) -> None: ...

class AugmentationStage(_message.Message):
    __slots__ = ("name", "args")
    class ArgsEntry(_message.Message):
        __slots__ = ("key", "value")
        KEY_FIELD_NUMBER: _ClassVar[int]
        VALUE_FIELD_NUMBER: _ClassVar[int]
        key: str
        value: float
        def __init__(self, key: _Optional[str] = ..., value: _Optional[float] = ...) -> None: ...
    NAME_FIELD_NUMBER: _ClassVar[int]
    ARGS_FIELD_NUMBER: _ClassVar[int]
    name: str
    args: _containers.ScalarMap[str, float]
    def __init__(self, name: _Optional[str] = ..., args: _Optional[_Mapping[str, float]] = ...) -> None: ...

class AugmentationPipeline(_message.Message):
    __slots__ = ("stages",)
    STAGES_FIELD_NUMBER: _ClassVar[int]
    stages: _containers.RepeatedCompositeFieldContainer[AugmentationStage]
    def __init__(self, stages: _Optional[_Iterable[_Union[AugmentationStage, _Mapping]]] = ...) -> None: ...

class SampleView(_message.Message):
    __slots__ = ("name", "of", "pipeline", "pipeline_text", "draws")
    NAME_FIELD_NUMBER: _ClassVar[int]
    OF_FIELD_NUMBER: _ClassVar[int]
    PIPELINE_FIELD_NUMBER: _ClassVar[int]
    PIPELINE_TEXT_FIELD_NUMBER: _ClassVar[int]
    DRAWS_FIELD_NUMBER: _ClassVar[int]
    name: str
    of: ViewOf
    pipeline: AugmentationPipeline
    pipeline_text: str
    draws: str
    def __init__(self, name: _Optional[str] = ..., of: _Optional[_Union[ViewOf, str]] = ..., pipeline: _Optional[_Union[AugmentationPipeline, _Mapping]] = ..., pipeline_text: _Optional[str] = ..., draws: _Optional[str] = ...) -> None: ...

class SampleBatchesRequest(_message.Message):
    __slots__ = ("session_id", "batch_size", "pipeline", "pipeline_text", "sharing", "prefetch", "seed", "min_size", "samples_per_insert", "error_buffer", "max_batches", "chunk_bytes", "source", "epochs", "per_env_augmentation", "include_next_obs", "views", "n_step", "discount", "sampler", "priority_exponent", "importance_sampling_exponent", "sequence")
    SESSION_ID_FIELD_NUMBER: _ClassVar[int]
    BATCH_SIZE_FIELD_NUMBER: _ClassVar[int]
    PIPELINE_FIELD_NUMBER: _ClassVar[int]
    PIPELINE_TEXT_FIELD_NUMBER: _ClassVar[int]
    SHARING_FIELD_NUMBER: _ClassVar[int]
    PREFETCH_FIELD_NUMBER: _ClassVar[int]
    SEED_FIELD_NUMBER: _ClassVar[int]
    MIN_SIZE_FIELD_NUMBER: _ClassVar[int]
    SAMPLES_PER_INSERT_FIELD_NUMBER: _ClassVar[int]
    ERROR_BUFFER_FIELD_NUMBER: _ClassVar[int]
    MAX_BATCHES_FIELD_NUMBER: _ClassVar[int]
    CHUNK_BYTES_FIELD_NUMBER: _ClassVar[int]
    SOURCE_FIELD_NUMBER: _ClassVar[int]
    EPOCHS_FIELD_NUMBER: _ClassVar[int]
    PER_ENV_AUGMENTATION_FIELD_NUMBER: _ClassVar[int]
    INCLUDE_NEXT_OBS_FIELD_NUMBER: _ClassVar[int]
    VIEWS_FIELD_NUMBER: _ClassVar[int]
    N_STEP_FIELD_NUMBER: _ClassVar[int]
    DISCOUNT_FIELD_NUMBER: _ClassVar[int]
    SAMPLER_FIELD_NUMBER: _ClassVar[int]
    PRIORITY_EXPONENT_FIELD_NUMBER: _ClassVar[int]
    IMPORTANCE_SAMPLING_EXPONENT_FIELD_NUMBER: _ClassVar[int]
    SEQUENCE_FIELD_NUMBER: _ClassVar[int]
    session_id: str
    batch_size: int
    pipeline: AugmentationPipeline
    pipeline_text: str
    sharing: DrawSharing
    prefetch: int
    seed: int
    min_size: int
    samples_per_insert: float
    error_buffer: float
    max_batches: int
    chunk_bytes: int
    source: BatchSource
    epochs: int
    per_env_augmentation: bool
    include_next_obs: bool
    views: _containers.RepeatedCompositeFieldContainer[SampleView]
    n_step: int
    discount: float
    sampler: Sampler
    priority_exponent: float
    importance_sampling_exponent: float
    sequence: SequenceRequest
    def __init__(self, session_id: _Optional[str] = ..., batch_size: _Optional[int] = ..., pipeline: _Optional[_Union[AugmentationPipeline, _Mapping]] = ..., pipeline_text: _Optional[str] = ..., sharing: _Optional[_Union[DrawSharing, str]] = ..., prefetch: _Optional[int] = ..., seed: _Optional[int] = ..., min_size: _Optional[int] = ..., samples_per_insert: _Optional[float] = ..., error_buffer: _Optional[float] = ..., max_batches: _Optional[int] = ..., chunk_bytes: _Optional[int] = ..., source: _Optional[_Union[BatchSource, str]] = ..., epochs: _Optional[int] = ..., per_env_augmentation: _Optional[bool] = ..., include_next_obs: _Optional[bool] = ..., views: _Optional[_Iterable[_Union[SampleView, _Mapping]]] = ..., n_step: _Optional[int] = ..., discount: _Optional[float] = ..., sampler: _Optional[_Union[Sampler, str]] = ..., priority_exponent: _Optional[float] = ..., importance_sampling_exponent: _Optional[float] = ..., sequence: _Optional[_Union[SequenceRequest, _Mapping]] = ...) -> None: ...

class SequenceRequest(_message.Message):
    __slots__ = ("length", "burn_in", "period", "boundary")
    LENGTH_FIELD_NUMBER: _ClassVar[int]
    BURN_IN_FIELD_NUMBER: _ClassVar[int]
    PERIOD_FIELD_NUMBER: _ClassVar[int]
    BOUNDARY_FIELD_NUMBER: _ClassVar[int]
    length: int
    burn_in: int
    period: int
    boundary: SequenceBoundary
    def __init__(self, length: _Optional[int] = ..., burn_in: _Optional[int] = ..., period: _Optional[int] = ..., boundary: _Optional[_Union[SequenceBoundary, str]] = ...) -> None: ...

class UpdatePrioritiesRequest(_message.Message):
    __slots__ = ("session_id", "keys", "priorities")
    SESSION_ID_FIELD_NUMBER: _ClassVar[int]
    KEYS_FIELD_NUMBER: _ClassVar[int]
    PRIORITIES_FIELD_NUMBER: _ClassVar[int]
    session_id: str
    keys: _containers.RepeatedScalarFieldContainer[int]
    priorities: _containers.RepeatedScalarFieldContainer[float]
    def __init__(self, session_id: _Optional[str] = ..., keys: _Optional[_Iterable[int]] = ..., priorities: _Optional[_Iterable[float]] = ...) -> None: ...

class UpdatePrioritiesResponse(_message.Message):
    __slots__ = ("updated", "missing")
    UPDATED_FIELD_NUMBER: _ClassVar[int]
    MISSING_FIELD_NUMBER: _ClassVar[int]
    updated: int
    missing: int
    def __init__(self, updated: _Optional[int] = ..., missing: _Optional[int] = ...) -> None: ...

class BatchChunk(_message.Message):
    __slots__ = ("batch_index", "field", "dtype", "shape", "offset", "field_bytes", "last", "data")
    BATCH_INDEX_FIELD_NUMBER: _ClassVar[int]
    FIELD_FIELD_NUMBER: _ClassVar[int]
    DTYPE_FIELD_NUMBER: _ClassVar[int]
    SHAPE_FIELD_NUMBER: _ClassVar[int]
    OFFSET_FIELD_NUMBER: _ClassVar[int]
    FIELD_BYTES_FIELD_NUMBER: _ClassVar[int]
    LAST_FIELD_NUMBER: _ClassVar[int]
    DATA_FIELD_NUMBER: _ClassVar[int]
    batch_index: int
    field: str
    dtype: DType
    shape: _containers.RepeatedScalarFieldContainer[int]
    offset: int
    field_bytes: int
    last: bool
    data: bytes
    def __init__(self, batch_index: _Optional[int] = ..., field: _Optional[str] = ..., dtype: _Optional[_Union[DType, str]] = ..., shape: _Optional[_Iterable[int]] = ..., offset: _Optional[int] = ..., field_bytes: _Optional[int] = ..., last: _Optional[bool] = ..., data: _Optional[bytes] = ...) -> None: ...

class SharedSampleRequest(_message.Message):
    __slots__ = ("start", "release")
    START_FIELD_NUMBER: _ClassVar[int]
    RELEASE_FIELD_NUMBER: _ClassVar[int]
    start: SampleBatchesRequest
    release: int
    def __init__(self, start: _Optional[_Union[SampleBatchesRequest, _Mapping]] = ..., release: _Optional[int] = ...) -> None: ...

class SharedSampleResponse(_message.Message):
    __slots__ = ("region", "batch")
    REGION_FIELD_NUMBER: _ClassVar[int]
    BATCH_FIELD_NUMBER: _ClassVar[int]
    region: SharedMemoryRegion
    batch: SharedBatch
    def __init__(self, region: _Optional[_Union[SharedMemoryRegion, _Mapping]] = ..., batch: _Optional[_Union[SharedBatch, _Mapping]] = ...) -> None: ...

class SharedMemoryRegion(_message.Message):
    __slots__ = ("size", "token", "slots", "slot_bytes", "socket")
    SIZE_FIELD_NUMBER: _ClassVar[int]
    TOKEN_FIELD_NUMBER: _ClassVar[int]
    SLOTS_FIELD_NUMBER: _ClassVar[int]
    SLOT_BYTES_FIELD_NUMBER: _ClassVar[int]
    SOCKET_FIELD_NUMBER: _ClassVar[int]
    size: int
    token: bytes
    slots: int
    slot_bytes: int
    socket: str
    def __init__(self, size: _Optional[int] = ..., token: _Optional[bytes] = ..., slots: _Optional[int] = ..., slot_bytes: _Optional[int] = ..., socket: _Optional[str] = ...) -> None: ...

class SharedTensor(_message.Message):
    __slots__ = ("dtype", "shape", "offset")
    DTYPE_FIELD_NUMBER: _ClassVar[int]
    SHAPE_FIELD_NUMBER: _ClassVar[int]
    OFFSET_FIELD_NUMBER: _ClassVar[int]
    dtype: DType
    shape: _containers.RepeatedScalarFieldContainer[int]
    offset: int
    def __init__(self, dtype: _Optional[_Union[DType, str]] = ..., shape: _Optional[_Iterable[int]] = ..., offset: _Optional[int] = ...) -> None: ...

class SharedBatch(_message.Message):
    __slots__ = ("batch_index", "slot", "shared", "tensors")
    class SharedEntry(_message.Message):
        __slots__ = ("key", "value")
        KEY_FIELD_NUMBER: _ClassVar[int]
        VALUE_FIELD_NUMBER: _ClassVar[int]
        key: str
        value: SharedTensor
        def __init__(self, key: _Optional[str] = ..., value: _Optional[_Union[SharedTensor, _Mapping]] = ...) -> None: ...
    class TensorsEntry(_message.Message):
        __slots__ = ("key", "value")
        KEY_FIELD_NUMBER: _ClassVar[int]
        VALUE_FIELD_NUMBER: _ClassVar[int]
        key: str
        value: Tensor
        def __init__(self, key: _Optional[str] = ..., value: _Optional[_Union[Tensor, _Mapping]] = ...) -> None: ...
    BATCH_INDEX_FIELD_NUMBER: _ClassVar[int]
    SLOT_FIELD_NUMBER: _ClassVar[int]
    SHARED_FIELD_NUMBER: _ClassVar[int]
    TENSORS_FIELD_NUMBER: _ClassVar[int]
    batch_index: int
    slot: int
    shared: _containers.MessageMap[str, SharedTensor]
    tensors: _containers.MessageMap[str, Tensor]
    def __init__(self, batch_index: _Optional[int] = ..., slot: _Optional[int] = ..., shared: _Optional[_Mapping[str, SharedTensor]] = ..., tensors: _Optional[_Mapping[str, Tensor]] = ...) -> None: ...
