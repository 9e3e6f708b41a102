"""The sizes of the method's data, defined once (docs/method.md sections 2-4).

An ORB descriptor is 32 bytes; the vocabulary has 64 words; a VLAD is 64 x 32 floats;
its binary code is one sign bit per float.
"""

DESCRIPTOR_BYTES = 32  # ORB; also the dimension of a descriptor as a vector of byte values
N_WORDS = 64  # vocabulary size k
VLAD_DIM = N_WORDS * DESCRIPTOR_BYTES  # 2048
CODE_BYTES = VLAD_DIM // 8  # 256: the sign bits of the VLAD
