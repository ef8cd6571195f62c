"""Alerting: events for the outbox, and their delivery to webhooks, Alertmanager, Slack and MQTT."""
