"""A tiny llama-architecture GGUF model with random weights, for a real llama.cpp server.

Two layers of width 64 (a 0.5 MB file, thousands of tokens a second on a CPU) and a
SentencePiece-style vocabulary that can spell any text: ``<unk> <s> </s>``, the 256
byte tokens ``<0x00>``..``<0xFF>``, and each printable ASCII character as a token of
its own (``▁`` for the space). The weights are random, so the text is noise; what
makes an answer parseable is the server's grammar for a JSON Schema.

The output head's rows of the special and byte tokens are zero: at temperature 0 the
model then writes printable ASCII and never ends by itself (``</s>`` is never the
largest logit), so a plain completion runs to ``max_tokens`` (what a deadline must
cut), while under a grammar the end comes when the JSON is complete.
"""

from __future__ import annotations

from pathlib import Path

import gguf
import numpy as np

LAYERS, WIDTH, HEADS, FEED_FORWARD = 2, 64, 4, 128
CONTEXT = 4096  # one token per character: the reasoner's prompt is about 1,700
SPECIAL = ("<unk>", "<s>", "</s>")
CHATML = ("{% for message in messages %}"
          "{{ '<|im_start|>' + message['role'] + '\n' + message['content'] + '<|im_end|>\n' }}"
          "{% endfor %}"
          "{% if add_generation_prompt %}{{ '<|im_start|>assistant\n' }}{% endif %}")


def vocabulary() -> tuple[list[str], list[float], list[int]]:
    """Tokens, scores and token types."""
    kinds = gguf.TokenType
    tokens = [*SPECIAL, *(f"<0x{b:02X}>" for b in range(256))]
    types = [kinds.UNKNOWN, kinds.CONTROL, kinds.CONTROL, *[kinds.BYTE] * 256]
    printable = ["\u2581" if c == 0x20 else chr(c) for c in range(0x20, 0x7F)]
    tokens += printable
    types += [kinds.NORMAL] * len(printable)
    scores = [0.0] * (len(tokens) - len(printable)) + [-float(i + 1)
                                                       for i in range(len(printable))]
    return tokens, scores, [int(t) for t in types]


def write_tiny_llama(path: Path, seed: int = 0) -> Path:
    rng = np.random.default_rng(seed)
    tokens, scores, types = vocabulary()
    head = WIDTH // HEADS

    def matrix(rows: int, cols: int, std: float) -> np.ndarray:
        return rng.normal(0.0, std, size=(rows, cols)).astype(np.float32)

    writer = gguf.GGUFWriter(str(path), "llama")
    writer.add_name("aesop-tiny-random-llama")
    writer.add_context_length(CONTEXT)
    writer.add_embedding_length(WIDTH)
    writer.add_block_count(LAYERS)
    writer.add_feed_forward_length(FEED_FORWARD)
    writer.add_head_count(HEADS)
    writer.add_head_count_kv(HEADS)
    writer.add_rope_dimension_count(head)
    writer.add_rope_freq_base(10000.0)
    writer.add_layer_norm_rms_eps(1e-5)
    writer.add_vocab_size(len(tokens))
    writer.add_file_type(gguf.LlamaFileType.ALL_F32)
    writer.add_tokenizer_model("llama")
    writer.add_tokenizer_pre("default")
    writer.add_token_list(tokens)
    writer.add_token_scores(scores)
    writer.add_token_types(types)
    writer.add_unk_token_id(0)
    writer.add_bos_token_id(1)
    writer.add_eos_token_id(2)
    writer.add_add_bos_token(True)
    writer.add_add_eos_token(False)
    writer.add_add_space_prefix(False)
    writer.add_chat_template(CHATML)

    ones = np.ones(WIDTH, dtype=np.float32)
    writer.add_tensor("token_embd.weight", matrix(len(tokens), WIDTH, 1.0))
    for i in range(LAYERS):
        block = f"blk.{i}."
        writer.add_tensor(block + "attn_norm.weight", ones.copy())
        for name in ("attn_q", "attn_k", "attn_v", "attn_output"):
            writer.add_tensor(block + name + ".weight", matrix(WIDTH, WIDTH, 0.2))
        writer.add_tensor(block + "ffn_norm.weight", ones.copy())
        writer.add_tensor(block + "ffn_gate.weight", matrix(FEED_FORWARD, WIDTH, 0.2))
        writer.add_tensor(block + "ffn_up.weight", matrix(FEED_FORWARD, WIDTH, 0.2))
        writer.add_tensor(block + "ffn_down.weight", matrix(WIDTH, FEED_FORWARD, 0.2))
    writer.add_tensor("output_norm.weight", ones.copy())
    output = matrix(len(tokens), WIDTH, 0.5)
    output[:len(SPECIAL) + 256] = 0.0  # see the module docstring
    writer.add_tensor("output.weight", output)
    writer.write_header_to_file()
    writer.write_kv_data_to_file()
    writer.write_tensors_to_file()
    writer.close()
    return path
