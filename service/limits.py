"""What the service accepts from a client, bounded: string lengths, keypoint counts, image pixels, and what
it echoes back in an error.

Why: a client's strings reach error details (gRPC trailers, 8 KiB at most by default: past it the
client gets RESOURCE_EXHAUSTED instead of the code that says what was wrong) and Track messages;
an image's declared size decides how much memory its decode takes (a 750 kB JPEG can declare
8000x6000, 144 MB decoded, and many GB in a network). Each limit is checked before any work, with
the code the field would get anyway: a name longer than any registered name is unknown (NOT_FOUND,
FAILED_PRECONDITION for a sequence), the rest is INVALID_ARGUMENT (INVALID_INPUT in a Track stream).
"""

from __future__ import annotations

from dataclasses import dataclass

from estimators.base import InvalidInput, UnknownEstimator, UnknownObject, UnknownSequence

DEFAULT_MAX_NAME_CHARS = 128
DEFAULT_MAX_KEYPOINTS = 1024
DEFAULT_MAX_IMAGE_PIXELS = 2048 * 2048  # 4.2 Mpx: 1920x1440 fits; frames are 640x480 in the normal case
MAX_MESSAGE_CHARS = 1024  # an error message sent to a client (gRPC details or a Track response's message)
ECHO_CHARS = 48  # the most of a client's own string an error message quotes


@dataclass(frozen=True)
class RequestLimits:
    max_name_chars: int = DEFAULT_MAX_NAME_CHARS  # estimator, object_id, sequence, session_id
    max_keypoints: int = DEFAULT_MAX_KEYPOINTS
    max_image_pixels: int = DEFAULT_MAX_IMAGE_PIXELS  # width x height, checked from the header before decoding

    def __post_init__(self) -> None:
        if self.max_name_chars < 1 or self.max_keypoints < 4 or self.max_image_pixels < 1:
            raise ValueError(f"--max-name-chars and --max-image-pixels must be >= 1 and --max-keypoints >= 4, got "
                             f"{self.max_name_chars}, {self.max_image_pixels}, {self.max_keypoints}")

    def check(self, request) -> None:
        """Raise the error the field would get for a request over a limit (before any other work)."""
        n = self.max_name_chars
        if len(request.estimator) > n:
            raise UnknownEstimator(f"unknown estimator {echo(request.estimator)}: names are at most {n} characters")
        if len(request.object_id) > n:
            raise UnknownObject(f"unknown object {echo(request.object_id)}: ids are at most {n} characters")
        if len(request.sequence) > n:
            raise UnknownSequence(f"unknown sequence {echo(request.sequence)}: names are at most {n} characters")
        if len(request.session_id) > n:
            raise InvalidInput(f"session_id is {len(request.session_id)} characters; at most {n} characters are accepted")
        if len(request.keypoints) > self.max_keypoints:
            raise InvalidInput(f"{len(request.keypoints)} keypoints; at most {self.max_keypoints} are accepted")
        image = request.image
        if image.width * image.height > self.max_image_pixels:
            raise InvalidInput(f"image of {image.width}x{image.height} ({image.width * image.height} pixels) is over "
                               f"the server's limit of {self.max_image_pixels} pixels")


def echo(text: str, limit: int = ECHO_CHARS) -> str:
    """A client's string quoted for an error message, cut to `limit` characters."""
    if len(text) <= limit:
        return repr(text)
    return repr(text[:limit]) + f"... ({len(text)} characters)"


def clip_message(message: str, limit: int = MAX_MESSAGE_CHARS) -> str:
    """An error message cut to `limit` characters (head and tail kept), so it always fits gRPC's trailers."""
    if len(message) <= limit:
        return message
    cut = f" [... {len(message) - limit} characters cut ...] "
    keep = max(0, limit - len(cut))
    return message[:keep - keep // 4] + cut + message[len(message) - keep // 4:]
