"""The one error type a user can cause; every layer may import it."""


class InputError(ValueError):
    """Bad user input. The message is one sentence naming the problem and what to do."""
