"""The stack on one machine: ``aesop up`` starts the services as processes and supervises them."""
