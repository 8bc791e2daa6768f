"""``avatar-prep`` stages: posing, UV atlas, UV texel projection, pose PCA, point hierarchy, localization."""
