"""schemathesis hooks for scripts/fuzz-http.sh.

A `grpc-timeout` header shorter than the work is answered 504 DEADLINE_EXCEEDED by design (the
deadline a client set has passed; tests/service/http.rs reaches it on purpose). The fuzzing
looks for 5xx that are faults, so generated requests go without that header.
"""

import schemathesis


@schemathesis.hook
def map_headers(ctx, headers):
    if headers:
        headers.pop("grpc-timeout", None)
    return headers


@schemathesis.hook
def before_call(ctx, case, **kwargs):
    # The coverage phase builds its cases without map_headers.
    if case.headers:
        case.headers.pop("grpc-timeout", None)
