"""schemathesis hooks for qemd (tests/schemathesis.sh): tus chunks are raw bytes."""

import schemathesis

# PATCH /v1/uploads/{id} takes `application/offset+octet-stream` (tus): serialise it as the
# bytes it is, like application/octet-stream.
schemathesis.serializer.alias("application/offset+octet-stream", "application/octet-stream")
