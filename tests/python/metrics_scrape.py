"""Scrapes a Tessera `/metrics` endpoint and parses it with the Prometheus
project's Python client (`prometheus_client`, its OpenMetrics parser, the
format the coordinator serves), printing every sample as JSON for
tests/operating.rs: [{"name", "labels", "value"}], plus each family's type.

Usage: metrics_scrape.py URL [TOKEN]. Exit 3 with the HTTP status and body
when the request is refused, 2 when prometheus_client is missing.
"""

import json
import sys
import urllib.error
import urllib.request

try:
    from prometheus_client.openmetrics.parser import text_string_to_metric_families
except ImportError:
    print("python3 lacks prometheus_client: python3 -m pip install prometheus_client", file=sys.stderr)
    sys.exit(2)

url = sys.argv[1]
req = urllib.request.Request(url)
if len(sys.argv) > 2:
    req.add_header("Authorization", "Bearer " + sys.argv[2])
try:
    with urllib.request.urlopen(req, timeout=10) as resp:
        ctype = resp.headers.get("Content-Type", "")
        text = resp.read().decode("utf-8")
except urllib.error.HTTPError as e:
    print(json.dumps({"status": e.code, "body": e.read().decode("utf-8", "replace")}))
    sys.exit(3)

samples = []
types = {}
for family in text_string_to_metric_families(text):
    types[family.name] = family.type
    for s in family.samples:
        samples.append({"name": s.name, "labels": s.labels, "value": s.value})
print(json.dumps({"content_type": ctype, "types": types, "samples": samples}))
