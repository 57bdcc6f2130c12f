"""saft.reconstruct"""
