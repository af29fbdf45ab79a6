"""Minimal PoseMatch client: register a template from a PNG, match it in an image, print poses.

Setup (once):
    pip install grpcio grpcio-tools
    python -m grpc_tools.protoc -I ../../proto --python_out=. --grpc_python_out=. \
        posematch/v1/posematch.proto
Run:
    python posematch_client.py localhost:50051 template.png image.png [--id part-17]
"""

import argparse
import sys
import uuid

import grpc

from posematch.v1 import posematch_pb2 as pb
from posematch.v1 import posematch_pb2_grpc as rpc


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("address")
    parser.add_argument("template")
    parser.add_argument("image")
    parser.add_argument("--id", default="", help="template ID (default: derived from content)")
    parser.add_argument("--timeout", type=float, default=5.0, help="deadline per call, seconds")
    args = parser.parse_args()

    with grpc.insecure_channel(args.address) as channel:
        stub = rpc.PoseMatcherStub(channel)
        with open(args.template, "rb") as f:
            info = stub.RegisterTemplate(
                pb.RegisterTemplateRequest(template_id=args.id, image=pb.Image(encoded=f.read())),
                timeout=args.timeout,
            )
        print(f"template {info.template_id}: {info.width}x{info.height}")
        with open(args.image, "rb") as f:
            request = pb.MatchRequest(
                template_id=info.template_id,
                image=pb.Image(encoded=f.read()),
                options=pb.MatchOptions(max_instances=5, min_score=0.5),
                request_id=str(uuid.uuid4()),
            )
        try:
            answer = stub.Match(request, timeout=args.timeout)
        except grpc.RpcError as error:  # the status says what to fix
            print(f"{error.code().name}: {error.details()}", file=sys.stderr)
            return 1
        for pose in answer.poses:
            print(
                f"x={pose.x:.2f} y={pose.y:.2f} angle={pose.angle_deg:.2f}° "
                f"sx={pose.scale_x:.3f} sy={pose.scale_y:.3f} score={pose.score:.3f}"
            )
        print(f"{answer.timings.total_ms:.1f} ms (network {answer.timings.network_ms:.1f} ms)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
