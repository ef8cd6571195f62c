"""Who may call what: the least role of every operation the API documents (tests/service/test_api_auth.py
checks each boundary over HTTP; tests/security/test_role_matrix.py that every route served has a decision).

A new route without an entry here fails both.
"""
from __future__ import annotations

# (method, OpenAPI path, least role) for every operation the API documents.
REQUIRED_ROLE = {
    ("get", "/api/v1/nodes"): "viewer",
    ("get", "/api/v1/nodes/{node_id}"): "viewer",
    ("patch", "/api/v1/nodes/{node_id}"): "admin",
    ("post", "/api/v1/nodes/{node_id}/decommission"): "admin",
    ("post", "/api/v1/nodes/{node_id}/recommission"): "admin",
    ("get", "/api/v1/nodes/{node_id}/measurements"): "viewer",
    ("get", "/api/v1/nodes/{node_id}/detections"): "viewer",
    ("get", "/api/v1/nodes/{node_id}/detections/latest"): "viewer",
    ("get", "/api/v1/nodes/{node_id}/baselines"): "viewer",
    ("post", "/api/v1/nodes/{node_id}/baselines"): "operator",
    ("post", "/api/v1/nodes/{node_id}/baselines/{baseline_id}/activate"): "operator",
    ("get", "/api/v1/measurements/{measurement_id}"): "viewer",
    ("get", "/api/v1/measurements/{measurement_id}/traces"): "viewer",
    ("get", "/api/v1/measurements/{measurement_id}/traces.npz"): "viewer",
    ("get", "/api/v1/measurements/{measurement_id}/traces.csv"): "viewer",
    ("post", "/api/v1/measurements/{measurement_id}/traces/request"): "operator",  # asks a gateway to upload
    ("get", "/api/v1/measurements/{measurement_id}/di-maps"): "viewer",
    ("get", "/api/v1/measurements/{measurement_id}/di-maps/{source}"): "viewer",
    ("get", "/api/v1/measurements/{measurement_id}/di-maps/{source}.png"): "viewer",
    ("get", "/api/v1/detections"): "viewer",
    ("get", "/api/v1/fleet/sites"): "viewer",
    ("get", "/api/v1/fleet/nodes"): "viewer",
    ("get", "/api/v1/alerts"): "viewer",
    ("get", "/api/v1/alerts/{alert_id}"): "viewer",
    ("post", "/api/v1/alerts/{alert_id}/acknowledge"): "operator",
    ("post", "/api/v1/alerts/{alert_id}/resolve"): "operator",
    ("get", "/api/v1/keys"): "admin",
    ("post", "/api/v1/keys"): "admin",
    ("delete", "/api/v1/keys/{key_id}"): "admin",
    ("post", "/api/v1/ingest/batches"): "gateway",
    ("get", "/api/v1/ingest/trace-requests"): "gateway",  # its own site's only
    ("post", "/api/v1/ingest/trace-requests/answers"): "gateway",
    ("get", "/metrics"): "viewer",
    ("get", "/healthz"): None,
    ("get", "/readyz"): None,
}
# A gateway key (the central site's ingest) reads and changes nothing else; no other key ingests.
WEAKER = {"viewer": ["gateway"], "operator": ["gateway", "viewer"], "admin": ["gateway", "viewer", "operator"],
          "gateway": ["viewer", "operator", "admin"]}
