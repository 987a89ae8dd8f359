"""Parses an OpenMetrics exposition from stdin with prometheus_client's own parser (the
one Prometheus' Python client uses) and prints every sample as one JSON line:
{"name": ..., "labels": {...}, "value": ...}. A text the parser refuses exits non-zero
with its error."""

import json
import sys

from prometheus_client.openmetrics.parser import text_string_to_metric_families


def main() -> None:
    text = sys.stdin.read()
    for family in text_string_to_metric_families(text):
        for s in family.samples:
            print(json.dumps({"name": s.name, "labels": s.labels, "value": s.value,
                              "type": family.type}))


if __name__ == "__main__":
    main()
