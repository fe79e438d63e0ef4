"""A generic gRPC client for Tessera (not the project's Rust code): submits a
scene and watches the job to completion. Stubs come from proto/ via
grpc_tools.protoc.
Usage: generic_client.py HOST:PORT SCENE.toml [--ca CA.pem] [--token TOKEN_FILE]
With --ca the channel is TLS, trusting that CA; --token sends the client
token as `authorization: Bearer TOKEN`."""
import argparse

import grpc
from tessera.v1 import common_pb2, jobs_pb2, jobs_pb2_grpc

p = argparse.ArgumentParser()
p.add_argument("addr")
p.add_argument("scene")
p.add_argument("--ca")
p.add_argument("--token")
args = p.parse_args()
addr, scene_path = args.addr, args.scene
with open(scene_path, "rb") as f:
    scene = f.read()

if args.ca:
    with open(args.ca, "rb") as f:
        channel = grpc.secure_channel(addr, grpc.ssl_channel_credentials(root_certificates=f.read()))
else:
    channel = grpc.insecure_channel(addr)
meta = [("tessera-protocol-version", "1")]
if args.token:
    with open(args.token) as f:
        meta.append(("authorization", "Bearer " + f.read().strip()))

with channel:
    jobs = jobs_pb2_grpc.JobServiceStub(channel)
    spec = jobs_pb2.JobSpec(
        name="from-python",
        scene_name=scene_path,
        scene=scene,
        overrides=common_pb2.RenderOverrides(width=64, height=48, samples=1),
    )
    job_id = jobs.SubmitJob(jobs_pb2.SubmitJobRequest(spec=spec), metadata=meta).job_id
    print("job", job_id, flush=True)
    last = None
    for event in jobs.WatchJob(jobs_pb2.WatchJobRequest(job_id=job_id), metadata=meta):
        last = event
        pct = 100.0 * event.samples_done / max(event.samples_total, 1)
        print("progress", jobs_pb2.JobState.Name(event.state), f"{pct:.1f}", flush=True)
    pct = 100.0 * last.samples_done / max(last.samples_total, 1)
    print("final", jobs_pb2.JobState.Name(last.state), f"{pct:.1f}", flush=True)
    raise SystemExit(0 if last.state == jobs_pb2.JOB_STATE_DONE else 1)
