"""The `region` estimator (docs/region.md): prior-guided, model-only pose refinement on the object's
outline, in the spirit of SRT3D. One job a file:

- viewpoint_model.py: contour points and normals for views on a geodesic sphere, built once, cached
- correspondence.py: correspondence lines and the probabilistic contour-position model along them
- histograms.py: foreground / background colour histograms
- optimizer.py: regularised Newton steps, coarse to fine; the covariance from the final Hessian
- estimator.py: the estimator the registry builds (kind `region`); its sessions' histograms live in
  `estimators.session_store`
"""
