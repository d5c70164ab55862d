from google.protobuf.internal import containers as _containers
from google.protobuf.internal import enum_type_wrapper as _enum_type_wrapper
from google.protobuf import descriptor as _descriptor
from google.protobuf import message as _message
from collections.abc import Iterable as _Iterable, Mapping as _Mapping
from typing import ClassVar as _ClassVar, Optional as _Optional, Union as _Union

DESCRIPTOR: _descriptor.FileDescriptor

class Image(_message.Message):
    __slots__ = ("encoding", "data", "width", "height")
    class Encoding(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
        __slots__ = ()
        ENCODING_UNSPECIFIED: _ClassVar[Image.Encoding]
        JPEG: _ClassVar[Image.Encoding]
        PNG: _ClassVar[Image.Encoding]
        RAW_RGB8: _ClassVar[Image.Encoding]
        RAW_GRAY8: _ClassVar[Image.Encoding]
    ENCODING_UNSPECIFIED: Image.Encoding
    JPEG: Image.Encoding
    PNG: Image.Encoding
    RAW_RGB8: Image.Encoding
    RAW_GRAY8: Image.Encoding
    ENCODING_FIELD_NUMBER: _ClassVar[int]
    DATA_FIELD_NUMBER: _ClassVar[int]
    WIDTH_FIELD_NUMBER: _ClassVar[int]
    HEIGHT_FIELD_NUMBER: _ClassVar[int]
    encoding: Image.Encoding
    data: bytes
    width: int
    height: int
    def __init__(self, encoding: _Optional[_Union[Image.Encoding, str]] = ..., data: _Optional[bytes] = ..., width: _Optional[int] = ..., height: _Optional[int] = ...) -> None: ...

class Intrinsics(_message.Message):
    __slots__ = ("fx", "fy", "cx", "cy", "width", "height", "distortion")
    FX_FIELD_NUMBER: _ClassVar[int]
    FY_FIELD_NUMBER: _ClassVar[int]
    CX_FIELD_NUMBER: _ClassVar[int]
    CY_FIELD_NUMBER: _ClassVar[int]
    WIDTH_FIELD_NUMBER: _ClassVar[int]
    HEIGHT_FIELD_NUMBER: _ClassVar[int]
    DISTORTION_FIELD_NUMBER: _ClassVar[int]
    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    distortion: _containers.RepeatedScalarFieldContainer[float]
    def __init__(self, fx: _Optional[float] = ..., fy: _Optional[float] = ..., cx: _Optional[float] = ..., cy: _Optional[float] = ..., width: _Optional[int] = ..., height: _Optional[int] = ..., distortion: _Optional[_Iterable[float]] = ...) -> None: ...

class Keypoint(_message.Message):
    __slots__ = ("id", "u", "v")
    ID_FIELD_NUMBER: _ClassVar[int]
    U_FIELD_NUMBER: _ClassVar[int]
    V_FIELD_NUMBER: _ClassVar[int]
    id: int
    u: float
    v: float
    def __init__(self, id: _Optional[int] = ..., u: _Optional[float] = ..., v: _Optional[float] = ...) -> None: ...

class Pose(_message.Message):
    __slots__ = ("tx", "ty", "tz", "qw", "qx", "qy", "qz")
    TX_FIELD_NUMBER: _ClassVar[int]
    TY_FIELD_NUMBER: _ClassVar[int]
    TZ_FIELD_NUMBER: _ClassVar[int]
    QW_FIELD_NUMBER: _ClassVar[int]
    QX_FIELD_NUMBER: _ClassVar[int]
    QY_FIELD_NUMBER: _ClassVar[int]
    QZ_FIELD_NUMBER: _ClassVar[int]
    tx: float
    ty: float
    tz: float
    qw: float
    qx: float
    qy: float
    qz: float
    def __init__(self, tx: _Optional[float] = ..., ty: _Optional[float] = ..., tz: _Optional[float] = ..., qw: _Optional[float] = ..., qx: _Optional[float] = ..., qy: _Optional[float] = ..., qz: _Optional[float] = ...) -> None: ...

class PoseCovariance(_message.Message):
    __slots__ = ("data",)
    DATA_FIELD_NUMBER: _ClassVar[int]
    data: _containers.RepeatedScalarFieldContainer[float]
    def __init__(self, data: _Optional[_Iterable[float]] = ...) -> None: ...

class PosePrior(_message.Message):
    __slots__ = ("pose", "covariance")
    POSE_FIELD_NUMBER: _ClassVar[int]
    COVARIANCE_FIELD_NUMBER: _ClassVar[int]
    pose: Pose
    covariance: PoseCovariance
    def __init__(self, pose: _Optional[_Union[Pose, _Mapping]] = ..., covariance: _Optional[_Union[PoseCovariance, _Mapping]] = ...) -> None: ...

class Crop(_message.Message):
    __slots__ = ("x", "y", "width", "height")
    X_FIELD_NUMBER: _ClassVar[int]
    Y_FIELD_NUMBER: _ClassVar[int]
    WIDTH_FIELD_NUMBER: _ClassVar[int]
    HEIGHT_FIELD_NUMBER: _ClassVar[int]
    x: int
    y: int
    width: int
    height: int
    def __init__(self, x: _Optional[int] = ..., y: _Optional[int] = ..., width: _Optional[int] = ..., height: _Optional[int] = ...) -> None: ...

class EstimateRequest(_message.Message):
    __slots__ = ("session_id", "frame_id", "capture_time_ns", "estimator", "object_id", "image", "intrinsics", "keypoints", "sequence", "client_state", "prior", "crop")
    SESSION_ID_FIELD_NUMBER: _ClassVar[int]
    FRAME_ID_FIELD_NUMBER: _ClassVar[int]
    CAPTURE_TIME_NS_FIELD_NUMBER: _ClassVar[int]
    ESTIMATOR_FIELD_NUMBER: _ClassVar[int]
    OBJECT_ID_FIELD_NUMBER: _ClassVar[int]
    IMAGE_FIELD_NUMBER: _ClassVar[int]
    INTRINSICS_FIELD_NUMBER: _ClassVar[int]
    KEYPOINTS_FIELD_NUMBER: _ClassVar[int]
    SEQUENCE_FIELD_NUMBER: _ClassVar[int]
    CLIENT_STATE_FIELD_NUMBER: _ClassVar[int]
    PRIOR_FIELD_NUMBER: _ClassVar[int]
    CROP_FIELD_NUMBER: _ClassVar[int]
    session_id: str
    frame_id: int
    capture_time_ns: int
    estimator: str
    object_id: str
    image: Image
    intrinsics: Intrinsics
    keypoints: _containers.RepeatedCompositeFieldContainer[Keypoint]
    sequence: str
    client_state: bytes
    prior: PosePrior
    crop: Crop
    def __init__(self, session_id: _Optional[str] = ..., frame_id: _Optional[int] = ..., capture_time_ns: _Optional[int] = ..., estimator: _Optional[str] = ..., object_id: _Optional[str] = ..., image: _Optional[_Union[Image, _Mapping]] = ..., intrinsics: _Optional[_Union[Intrinsics, _Mapping]] = ..., keypoints: _Optional[_Iterable[_Union[Keypoint, _Mapping]]] = ..., sequence: _Optional[str] = ..., client_state: _Optional[bytes] = ..., prior: _Optional[_Union[PosePrior, _Mapping]] = ..., crop: _Optional[_Union[Crop, _Mapping]] = ...) -> None: ...

class EstimateResponse(_message.Message):
    __slots__ = ("frame_id", "capture_time_ns", "status", "message", "pose", "confidence", "estimator", "server_time_ms", "stage_ms", "pose_covariance")
    class Status(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
        __slots__ = ()
        STATUS_UNSPECIFIED: _ClassVar[EstimateResponse.Status]
        OK: _ClassVar[EstimateResponse.Status]
        OBJECT_NOT_FOUND: _ClassVar[EstimateResponse.Status]
        INVALID_INPUT: _ClassVar[EstimateResponse.Status]
        INTERNAL: _ClassVar[EstimateResponse.Status]
        UNAVAILABLE: _ClassVar[EstimateResponse.Status]
    STATUS_UNSPECIFIED: EstimateResponse.Status
    OK: EstimateResponse.Status
    OBJECT_NOT_FOUND: EstimateResponse.Status
    INVALID_INPUT: EstimateResponse.Status
    INTERNAL: EstimateResponse.Status
    UNAVAILABLE: EstimateResponse.Status
    class StageMsEntry(_message.Message):
        __slots__ = ("key", "value")
        KEY_FIELD_NUMBER: _ClassVar[int]
        VALUE_FIELD_NUMBER: _ClassVar[int]
        key: str
        value: float
        def __init__(self, key: _Optional[str] = ..., value: _Optional[float] = ...) -> None: ...
    FRAME_ID_FIELD_NUMBER: _ClassVar[int]
    CAPTURE_TIME_NS_FIELD_NUMBER: _ClassVar[int]
    STATUS_FIELD_NUMBER: _ClassVar[int]
    MESSAGE_FIELD_NUMBER: _ClassVar[int]
    POSE_FIELD_NUMBER: _ClassVar[int]
    CONFIDENCE_FIELD_NUMBER: _ClassVar[int]
    ESTIMATOR_FIELD_NUMBER: _ClassVar[int]
    SERVER_TIME_MS_FIELD_NUMBER: _ClassVar[int]
    STAGE_MS_FIELD_NUMBER: _ClassVar[int]
    POSE_COVARIANCE_FIELD_NUMBER: _ClassVar[int]
    frame_id: int
    capture_time_ns: int
    status: EstimateResponse.Status
    message: str
    pose: Pose
    confidence: float
    estimator: str
    server_time_ms: float
    stage_ms: _containers.ScalarMap[str, float]
    pose_covariance: PoseCovariance
    def __init__(self, frame_id: _Optional[int] = ..., capture_time_ns: _Optional[int] = ..., status: _Optional[_Union[EstimateResponse.Status, str]] = ..., message: _Optional[str] = ..., pose: _Optional[_Union[Pose, _Mapping]] = ..., confidence: _Optional[float] = ..., estimator: _Optional[str] = ..., server_time_ms: _Optional[float] = ..., stage_ms: _Optional[_Mapping[str, float]] = ..., pose_covariance: _Optional[_Union[PoseCovariance, _Mapping]] = ...) -> None: ...

class ListEstimatorsRequest(_message.Message):
    __slots__ = ()
    def __init__(self) -> None: ...

class EstimatorInfo(_message.Message):
    __slots__ = ("name", "kind", "version", "objects", "ready", "is_default", "description")
    NAME_FIELD_NUMBER: _ClassVar[int]
    KIND_FIELD_NUMBER: _ClassVar[int]
    VERSION_FIELD_NUMBER: _ClassVar[int]
    OBJECTS_FIELD_NUMBER: _ClassVar[int]
    READY_FIELD_NUMBER: _ClassVar[int]
    IS_DEFAULT_FIELD_NUMBER: _ClassVar[int]
    DESCRIPTION_FIELD_NUMBER: _ClassVar[int]
    name: str
    kind: str
    version: str
    objects: _containers.RepeatedScalarFieldContainer[str]
    ready: bool
    is_default: bool
    description: str
    def __init__(self, name: _Optional[str] = ..., kind: _Optional[str] = ..., version: _Optional[str] = ..., objects: _Optional[_Iterable[str]] = ..., ready: _Optional[bool] = ..., is_default: _Optional[bool] = ..., description: _Optional[str] = ...) -> None: ...

class ListEstimatorsResponse(_message.Message):
    __slots__ = ("estimators",)
    ESTIMATORS_FIELD_NUMBER: _ClassVar[int]
    estimators: _containers.RepeatedCompositeFieldContainer[EstimatorInfo]
    def __init__(self, estimators: _Optional[_Iterable[_Union[EstimatorInfo, _Mapping]]] = ...) -> None: ...
