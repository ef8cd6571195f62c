"""HTTP routes: thin functions that validate, call service modules and return typed models."""
