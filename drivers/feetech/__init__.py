"""Feetech STS/SMS and SCS serial bus servos (the SO-100 / SO-101 arms): issue 26."""
