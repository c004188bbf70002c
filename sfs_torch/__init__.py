"""sfs-torch"""
