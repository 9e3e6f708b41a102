"""Pure vision core of the map server: ORB features, vocabulary, VLAD, binary codes,
Hamming matching, PnP and pose hypotheses (docs/method.md sections 2-6).

Every function takes arrays and a frozen config and returns arrays; the only file I/O is
reading and writing vocabularies (``vocabulary.py``).
"""
