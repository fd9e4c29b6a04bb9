"""Schemathesis hooks for the portal's API (loaded through SCHEMATHESIS_HOOKS
by tests/python/api_fuzz.py): serializers for the bodies the API takes as
raw bytes, and the check that no answer shows a path of the server's."""

import os

import schemathesis

# Text no answer may contain: the store's folder, the compile cache, the
# repository, the home folder (api_fuzz.py passes them, one per line).
FORBIDDEN = [line for line in os.environ.get("API_FUZZ_FORBIDDEN", "").splitlines() if line.strip()]


def _as_bytes(value):
    if value is None:
        return b""
    if isinstance(value, bytes):
        return value
    if isinstance(value, str):
        return value.encode("utf-8", "surrogatepass")
    return repr(value).encode()


@schemathesis.serializer("application/wasm")
def wasm(ctx, value):
    """A component upload: whatever bytes the generator made."""
    return _as_bytes(value)


@schemathesis.serializer("application/xml")
def xml(ctx, value):
    """A robot file: the generated text as it is (the host parses it)."""
    return _as_bytes(value)


@schemathesis.check
def no_server_path(ctx, response, case):
    """No answer shows where the server keeps its files."""
    text = response.content.decode("utf-8", "replace") if response.content else ""
    for header, value in response.headers.items():
        values = value if isinstance(value, (list, tuple)) else [value]
        text += "".join(f"\n{header}: {v}" for v in values)
    for path in FORBIDDEN:
        if path in text:
            at = text.index(path)
            raise AssertionError(f"the answer shows the server path {path!r}: ...{text[max(0, at - 80):at + 80]!r}...")
