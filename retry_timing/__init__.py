"""When to try again: exponential backoff with a chosen jitter, for every retry in PipeSentry (pure)."""
