"""The AESOP services and the `aesop` command."""
