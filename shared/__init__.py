"""Code every AESOP service uses: messages, topics, settings, the Zenoh bus."""
