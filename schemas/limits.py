"""Hard size limits of the contract; the service may lower them through its settings."""

MAX_NAME_LENGTH = 64
MAX_EXPRESSION_LENGTH = 4000
MAX_STATES = 200
MAX_PARAMETERS = 500
MAX_EXPERIMENTS = 100
MAX_SAMPLES = 1_000_000
NAME_PATTERN = r"^[A-Za-z_][A-Za-z0-9_]*$"
